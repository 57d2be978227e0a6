"""Shared timing and table helpers for the benchmarks."""

from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Callable, Iterator

import numpy as np

from pcc_ros.tables import print_table  # noqa: F401  (the benchmarks import it from here)


@contextlib.contextmanager
def inference_path(completer, path: str) -> Iterator[None]:
    """``completer`` on inference ``path`` (:mod:`pcc_ros.models.inference`) inside the block, its
    own after: the alternatives a benchmark times on one completer and one set of weights (set
    between calls, never while another thread runs it)."""
    before = completer.inference_path
    completer.inference_path = path
    try:
        yield
    finally:
        completer.inference_path = before


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
    alternatives: dict[str, Callable[[], object]], repeat: int, warmup: int = 2,
    cpu_times: dict[str, np.ndarray] | None = None,
) -> dict[str, np.ndarray]:
    """Seconds per call of each alternative, timed round-robin (one call of each per round).

    Interleaving makes machine load (this is a shared machine) hit every alternative alike,
    and no alternative runs with caches warmed by a block of its own repeats. ``cpu_times``:
    filled with the calling thread's CPU seconds of each call too (single-threaded work).
    """
    for _ in range(warmup):
        for fn in alternatives.values():
            fn()
    times = {k: np.empty(repeat) for k in alternatives}
    cpu = {k: np.empty(repeat) for k in alternatives}
    for r in range(repeat):
        for name, fn in alternatives.items():
            tic, cpu_tic = time.perf_counter(), time.thread_time()
            fn()
            times[name][r] = time.perf_counter() - tic
            cpu[name][r] = time.thread_time() - cpu_tic
    if cpu_times is not None:
        cpu_times.update(cpu)
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


def _busy_seconds() -> float | None:
    """CPU seconds every process on the machine has spent busy since boot (``/proc/stat``'s
    first line, idle and iowait left out); None where there is no ``/proc/stat``."""
    try:
        with open("/proc/stat") as f:
            values = [int(v) for v in f.readline().split()[1:]]
    except (OSError, ValueError):
        return None
    idle = values[3] + (values[4] if len(values) > 4 else 0)
    return (sum(values[:8]) - idle) / os.sysconf("SC_CLK_TCK")


class OtherLoad:
    """How busy the machine was with *other* processes while a benchmark ran: the machine's
    busy CPU seconds (``/proc/stat``) minus this process's own (``os.times``), per second of
    wall time, in cores. The load average cannot tell: it counts the benchmark's own threads
    (and the preceding benchmark's, for a minute), so an idle machine running a 2-thread
    benchmark reads 1-2. ``cores`` is None where ``/proc/stat`` is missing."""

    def __enter__(self) -> OtherLoad:
        self._wall, self._busy, self._own = time.perf_counter(), _busy_seconds(), self._own_seconds()
        self.cores: float | None = None
        return self

    def __exit__(self, *exc) -> None:
        busy = _busy_seconds()
        if busy is not None and self._busy is not None:
            wall = max(time.perf_counter() - self._wall, 1e-9)
            self.cores = max(0.0, (busy - self._busy) - (self._own_seconds() - self._own)) / wall

    @staticmethod
    def _own_seconds() -> float:
        t = os.times()
        return t.user + t.system  # every thread of this process (children are not ours to count)
