"""Which occurrences of a repeating event are logged: the package's one rate-limit rule.

A condition that can repeat at the scan rate (an invalid box in every message, messages that
never pair, a blocked sensor, logits where probabilities belong) must neither flood a node's
log nor go unsaid: its occurrences are counted (the counts are on ``/diagnostics`` or in the
line itself) and :func:`worth_logging` says which of them get a line.
"""

from __future__ import annotations


def worth_logging(count: int, previous: int | None = None, every: int | None = None) -> bool:
    """Whether to log now that an event has happened ``count`` times (counted from 1).

    Default: at the 1st, 10th, 100th, 1000th ... occurrence (a persistent condition is said ever
    more rarely, with its running count). ``every=N``: at the 1st and then every Nth after it
    (1, N + 1, 2N + 1 ...: a reminder at a steady rate). ``previous``: the count when last asked
    (default ``count - 1``), for a count that moves by more than one at a time (a batch of
    events): true when any occurrence in ``(previous, count]`` is one to log.
    """
    previous = count - 1 if previous is None else previous
    if count < 1 or count <= previous:
        return False
    if every is None:
        return 10 ** (len(str(count)) - 1) > previous  # the largest power of ten <= count is new
    return (count - 1) // every > (previous - 1) // every
