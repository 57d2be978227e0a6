"""geometry.segments: positions within runs laid end to end."""

import numpy as np

from pcc_ros.geometry.segments import positions_in_runs


def test_positions_in_runs_matches_a_loop():
    lengths = np.array([3, 0, 1, 4, 0])
    expected = np.concatenate([np.arange(n) for n in lengths])
    got = positions_in_runs(lengths)
    assert got.dtype == np.int64 and np.array_equal(got, expected)


def test_positions_in_runs_of_nothing_is_empty():
    assert positions_in_runs(np.zeros(0, np.int64)).shape == (0,)
    assert positions_in_runs(np.zeros(3, np.int32)).shape == (0,)
