"""Index arithmetic on runs laid end to end (a ragged array's rows, a box's cells, a ray's
crossings): the loop-free building block the crop, the filter, AML's ray marching and the
instance cache share."""

from __future__ import annotations

import numpy as np


def positions_in_runs(lengths: np.ndarray) -> np.ndarray:
    """``0 .. n - 1`` for each ``n`` of ``lengths`` (non-negative integers), concatenated (int64).

    With ``np.repeat(np.arange(len(lengths)), lengths)`` beside it, this walks every element of
    every run without a Python loop."""
    lengths = np.asarray(lengths, dtype=np.int64)
    return np.arange(int(lengths.sum()), dtype=np.int64) - np.repeat(np.cumsum(lengths) - lengths, lengths)
