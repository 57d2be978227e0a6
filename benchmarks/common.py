"""Shared timing and table helpers for the benchmarks."""

from __future__ import annotations

import os
import time
from collections.abc import Callable

import numpy as np

from pcc_ros.tables import print_table  # noqa: F401  (the benchmarks import it from here)


def median_ms(fn: Callable[[], object], repeat: int = 30, warmup: int = 3) -> float:
    """Median wall time of ``fn()`` in milliseconds over ``repeat`` runs after ``warmup``."""
    for _ in range(warmup):
        fn()
    times = np.empty(repeat)
    for i in range(repeat):
        start = time.perf_counter()
        fn()
        times[i] = time.perf_counter() - start
    return float(np.median(times) * 1e3)


def interleaved(
    alternatives: dict[str, Callable[[], object]], repeat: int, warmup: int = 2
) -> dict[str, np.ndarray]:
    """Seconds per call of each alternative, timed round-robin (one call of each per round).

    Interleaving makes machine load (this is a shared machine) hit every alternative alike,
    and no alternative runs with caches warmed by a block of its own repeats.
    """
    for _ in range(warmup):
        for fn in alternatives.values():
            fn()
    times = {k: np.empty(repeat) for k in alternatives}
    for r in range(repeat):
        for name, fn in alternatives.items():
            tic = time.perf_counter()
            fn()
            times[name][r] = time.perf_counter() - tic
    return times


def summary_ms(seconds: np.ndarray) -> dict[str, float]:
    """min / median / p95 / max of timings in seconds, as milliseconds."""
    ms = np.asarray(seconds, dtype=np.float64) * 1e3
    return {"min_ms": float(ms.min()), "median_ms": float(np.median(ms)),
            "p95_ms": float(np.percentile(ms, 95)), "max_ms": float(ms.max()), "n": int(ms.size)}


def load_average() -> list[float]:
    """The machine's 1 / 5 / 15-minute load averages (recorded with every benchmark)."""
    try:
        return [float(v) for v in os.getloadavg()]
    except OSError:  # not available on this platform
        return [float("nan")] * 3


def machine() -> dict[str, object]:
    """Cores and load, for the JSON of a benchmark."""
    return {"cpu_count": os.cpu_count(), "load_average": load_average()}
