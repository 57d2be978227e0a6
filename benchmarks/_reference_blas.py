"""The compiled loops' products as they were before the public BLAS routes: MKL's Fortran
``sgemm_`` taken out of ``libtorch_cpu.so`` by symbol name, kept as the "today's kernels" side
of ``pcc bench complete`` (the ``fast_libtorch`` column); nothing else uses it.

Why a benchmark keeps it: the issue that removed the binding from the package (it exists only in
x86 torch builds with MKL, and pins torch to one version) asked for the new routes to keep 90 %
of its 1-thread throughput, and only the same loops with the old products, timed in the same
rounds, measure that. It is a route type of :func:`pcc_ros.models.blas.gemm` (an overload
registered here), so the loops are the package's own and only the product differs, called as the
old kernels called it (column-major ``c^T = b^T a^T``, every argument by reference, MKL's thread
count torch's: ``torch.set_num_threads`` sets it).

:func:`available` is False where this torch build has no ``sgemm_`` (another CPU, a torch without
MKL): the benchmark then leaves the column out and says why.
"""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Iterator
from pathlib import Path
from typing import NamedTuple

import numpy as np
from numba import types
from numba.core.caching import NullCache
from numba.core.dispatcher import Dispatcher
from numba.extending import overload

from pcc_ros.models.blas import data_pointer, gemm, route_is

#: The name the symbol is registered under for the compiled code (not ``sgemm_``, which MKL's
#: own library, when loaded, also exports).
SYMBOL = "pcc_reference_libtorch_sgemm"


class LibtorchSgemm(NamedTuple):
    """Products by libtorch's ``sgemm_`` (the kernels before the public BLAS routes)."""


@functools.cache
def available() -> str | None:
    """None where libtorch's ``sgemm_`` is registered for the compiled code, else why not."""
    import ctypes

    import llvmlite.binding
    import torch

    path = Path(torch.__file__).parent / "lib" / "libtorch_cpu.so"
    try:
        address = ctypes.cast(ctypes.CDLL(str(path)).sgemm_, ctypes.c_void_p).value
    except (OSError, AttributeError) as exc:
        return f"no sgemm_ in {path.name} ({exc})"
    llvmlite.binding.add_symbol(SYMBOL, address)
    return None


_sgemm = types.ExternalFunction(SYMBOL, types.void(*([types.voidptr] * 13)))


@overload(gemm)
def _gemm(blas, a, b, c):
    if not route_is(blas, LibtorchSgemm):
        return None

    def sgemm(blas, a, b, c):
        ints, floats, chars = np.empty(6, np.int32), np.empty(2, np.float32), np.full(1, 78, np.uint8)  # "N"
        m, k = a.shape
        n = b.shape[1]
        ints[0], ints[1], ints[2] = n, m, k
        ints[3], ints[4], ints[5] = max(b.strides[0] // 4, n), max(a.strides[0] // 4, k), max(c.strides[0] // 4, n)
        floats[0], floats[1] = 1.0, 0.0
        p = data_pointer
        _sgemm(p(chars), p(chars), p(ints[0:]), p(ints[1:]), p(ints[2:]), p(floats[0:]), p(b), p(ints[3:]), p(a),
               p(ints[4:]), p(floats[1:]), p(c), p(ints[5:]))

    return sgemm


@contextlib.contextmanager
def uncached(module) -> Iterator[None]:
    """Compile ``module``'s kernels for :class:`LibtorchSgemm` inside this block without writing
    them to the kernel cache: a cache index names the argument types, and one naming this
    benchmark-only class could not be read by a process that cannot import it (a node)."""
    found = [d for d in vars(module).values() if isinstance(d, Dispatcher)]
    saved = [d._cache for d in found]
    for d in found:
        d._cache = NullCache()
    try:
        yield
    finally:
        for d, cache in zip(found, saved):
            d._cache = cache


@contextlib.contextmanager
def routed(route) -> Iterator[None]:
    """The compiled loops' products on ``route`` inside the block (:func:`pcc_ros.models.blas.route`
    swapped: process-wide, so a benchmark sets it between calls, never while another thread runs)."""
    from pcc_ros.models import blas

    before = blas.route
    blas.route = lambda: route
    try:
        yield
    finally:
        blas.route = before
