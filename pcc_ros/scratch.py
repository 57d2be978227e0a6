"""Per-thread work arrays kept from call to call (the scan-sized temporaries of a frame).

A fresh array's pages cost the kernel a fault each on first touch (measured on the 2-core
development VM: about 4 us per 4 KiB page), and numpy's allocator hands large blocks back to
the system between frames, so megabytes of temporaries are faulted in again every frame;
buffers kept from frame to frame are touched warm. Each module that wants this keeps its own
:class:`Scratch` (names are per pool: two modules never share a buffer by accident), and every
thread sees its own buffers (the node's workers run the same code side by side).
"""

from __future__ import annotations

import threading

import numpy as np

#: A buffer larger than this (a hostile frame) is handed out but not kept.
MAX_KEPT_BYTES = 64 << 20


class Scratch(threading.local):
    """A pool of named work arrays, one set per thread. What it returns is only valid until
    the same name is asked for again in the same thread: never hand one to a caller."""

    def __init__(self) -> None:
        self.buffers: dict[str, np.ndarray] = {}

    def __call__(self, name: str, n: int, dtype) -> np.ndarray:
        """A length-``n`` array of ``dtype`` (contents undefined), the same memory each call."""
        buf = self.buffers.get(name)
        if buf is None or buf.dtype != dtype or len(buf) < n:
            buf = np.empty(n + n // 4 + 1024, dtype)
            if buf.nbytes <= MAX_KEPT_BYTES:
                self.buffers[name] = buf
        return buf[:n]

    def whole(self, name: str, dtype) -> np.ndarray:
        """All of ``name``'s buffer (empty if none yet), for a compiled kernel that sizes its
        own work memory and grows it when short; :meth:`keep` what it returns."""
        buf = self.buffers.get(name)
        return buf if buf is not None and buf.dtype == dtype else np.empty(0, dtype)

    def keep(self, name: str, buf: np.ndarray) -> None:
        """Hand ``buf`` out for ``name`` from now on (see :meth:`whole`)."""
        if buf.nbytes <= MAX_KEPT_BYTES:
            self.buffers[name] = buf

    def nonzero(self, mask: np.ndarray, name: str) -> np.ndarray:
        """``np.flatnonzero(mask)`` into a kept buffer (through a transient array: numpy's
        nonzero and a copy cost about half of ``np.compress`` into the buffer)."""
        found = np.flatnonzero(mask)
        out = self(name, len(found), np.int64)
        np.copyto(out, found)
        return out

    def runs(self, lo: np.ndarray, length: np.ndarray, name: str) -> np.ndarray:
        """The concatenated ranges ``lo[i] .. lo[i] + length[i] - 1`` (int64): a step of 1
        everywhere but at the run starts, one cumulative sum."""
        lo, length = lo[length > 0], length[length > 0]
        out = self(name, int(length.sum()), np.int64)
        if len(lo):
            out.fill(1)
            first = np.cumsum(length) - length
            out[first[0]] = lo[0]
            out[first[1:]] = lo[1:] - (lo[:-1] + length[:-1] - 1)
            np.cumsum(out, out=out)
        return out
