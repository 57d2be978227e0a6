"""pcc_ros.scratch: work arrays kept per thread, capped, with the helpers the passes use."""

import threading

import numpy as np

from pcc_ros import scratch
from pcc_ros.scratch import Scratch


def test_same_memory_each_call_and_regrown_when_too_small():
    ws = Scratch()
    a = ws("a", 100, np.float32)
    assert np.shares_memory(a, ws("a", 50, np.float32))
    bigger = ws("a", 10_000, np.float32)
    assert len(bigger) == 10_000 and not np.shares_memory(a, bigger)
    assert ws("a", 100, np.int64).dtype == np.int64  # another dtype: another array


def test_oversized_buffers_are_not_kept(monkeypatch):
    monkeypatch.setattr(scratch, "MAX_KEPT_BYTES", 1024)
    ws = Scratch()
    a = ws("big", 10_000, np.float64)
    assert "big" not in ws.buffers and not np.shares_memory(a, ws("big", 10_000, np.float64))


def test_threads_get_their_own_buffers():
    ws = Scratch()
    mine = ws("x", 10, np.float64)
    theirs = []
    t = threading.Thread(target=lambda: theirs.append(ws("x", 10, np.float64)))
    t.start()
    t.join()
    assert not np.shares_memory(mine, theirs[0])


def test_nonzero_and_runs_match_numpy():
    ws = Scratch()
    mask = np.random.default_rng(0).random(1000) < 0.3
    assert np.array_equal(ws.nonzero(mask, "nz"), np.flatnonzero(mask))
    lo, length = np.array([5, 0, 40, 7]), np.array([3, 0, 2, 1])
    expected = np.concatenate([np.arange(a, a + n) for a, n in zip(lo, length)])
    assert np.array_equal(ws.runs(lo, length, "r"), expected)
    assert len(ws.runs(np.zeros(0, np.int64), np.zeros(0, np.int64), "r")) == 0
