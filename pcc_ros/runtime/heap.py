"""Keep Python's cyclic garbage collector off the frame path of a long-running node.

A loaded node holds a few hundred thousand long-lived objects (torch modules, numpy arrays,
the message type store). Every frame makes and drops about a thousand message objects, so the
collector runs often, and now and then a full (generation 2) pass walks every one of those
long-lived objects: a 110-120 ms stall in one frame's encode stage in ``pcc bench pipeline``
(once in 30-90 frames at 20 cars), for objects that live as long as the process.
``gc.freeze()`` moves every object alive at start-up into the permanent generation, which the
collector never walks; a frame's garbage is still collected as before.
"""

from __future__ import annotations

import gc


def freeze_long_lived() -> int:
    """Exclude every object alive now from future collections; returns how many are frozen.

    Called at a node's start-up and after a long-lived part was replaced (a backend reloaded
    at run time). The frozen objects are made collectable again and one full collection runs
    first (about 50 ms with torch loaded, off the frame path): ``gc.freeze`` alone would also
    freeze the unreachable reference cycles waiting for the collector -- an old backend, or a
    node core dropped earlier in the same process (``pcc demo``'s replays, the test suite) --
    and keep them for good."""
    gc.unfreeze()
    gc.collect()
    gc.freeze()
    return gc.get_freeze_count()
