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
    """Exclude every object alive now from future collections (start-up: O(1), no collection
    pass); returns how many objects are frozen."""
    gc.freeze()
    return gc.get_freeze_count()


def refreeze_after_swap() -> int:
    """After a long-lived part was replaced (a backend reloaded at run time): make the frozen
    objects collectable again, collect (the old backend's reference cycles are freed now, not
    kept forever), and freeze what is alive. One full pass, off the frame path of a rare event."""
    gc.unfreeze()
    gc.collect()
    return freeze_long_lived()
