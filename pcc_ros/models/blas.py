"""The matrix products of the compiled CPU loops (:mod:`pcc_ros.models.kernels`): two routes to a
BLAS, both through public interfaces, chosen by what the machine has.

* :class:`Cblas`: ``cblas_sgemm``, the standard C interface of Intel's oneAPI MKL, from the
  ``mkl`` wheel's ``libmkl_rt`` (x86-64; ``requirements.txt`` installs it there), loaded by
  llvmlite and called from the compiled code as an external function, on MKL's sequential
  threading layer (one thread per calling thread: the completer's ``workers`` give the
  parallelism) and its 32-bit-integer interface, both set through MKL's documented
  ``MKL_Set_Threading_Layer`` / ``MKL_Set_Interface_Layer`` (settings of that library in the
  process: another user of the same ``libmkl_rt`` there runs sequential too).
* :class:`NumpyDot`: ``np.dot`` inside the compiled code, which numba hands to SciPy's BLAS
  (``scipy.linalg.cython_blas``; OpenBLAS in the pip wheels), wherever SciPy runs.

Why two: at the network's narrow layers (16-128 inputs, a few hundred to a few thousand rows per
product) OpenBLAS 0.3.30 runs 15-40 % slower than MKL on this project's x86 machines, which made
the whole network 0.8x as fast (``pcc bench complete`` compares the routes). :func:`route` takes
:class:`Cblas` where ``libmkl_rt`` loads and accepts those settings, :class:`NumpyDot`
elsewhere (another CPU, no ``mkl`` installed, a process whose MKL was already set up otherwise);
both give the same values within float rounding (``test/test_blas.py``).

A route is a value the kernels take as an argument: its type selects the product at compile
time (:func:`gemm`), so each route's kernels are compiled and cached apart, and a process without
MKL never loads code that calls it. Routes are empty tuples, all equal to each other: tell them
apart by type.
"""

from __future__ import annotations

import functools
import importlib.metadata
import logging
import sys
from pathlib import Path
from typing import NamedTuple

import numpy as np
from numba import types
from numba.core import cgutils
from numba.core.errors import TypingError
from numba.extending import intrinsic, overload

from pcc_ros.jit import compiled

log = logging.getLogger(__name__)


class NumpyDot(NamedTuple):
    """Products by numba's ``np.dot`` (SciPy's BLAS)."""


class Cblas(NamedTuple):
    """Products by MKL's ``cblas_sgemm`` (``libmkl_rt``, sequential)."""


#: MKL's documented constants (``mkl_service.h``, ``mkl_cblas.h``).
MKL_THREADING_SEQUENTIAL = 1
MKL_INTERFACE_LP64 = 0
CBLAS_ROW_MAJOR, CBLAS_NO_TRANS = 101, 111

_int = types.int32  # MKL_INT on the LP64 interface; the enums are C ints
_cblas_sgemm = types.ExternalFunction("cblas_sgemm", types.void(
    _int, _int, _int, _int, _int, _int, types.float32, types.voidptr, _int, types.voidptr, _int, types.float32,
    types.voidptr, _int))
_set_threading_layer = types.ExternalFunction("MKL_Set_Threading_Layer", types.int32(types.int32))
_set_interface_layer = types.ExternalFunction("MKL_Set_Interface_Layer", types.int32(types.int32))


def mkl_library() -> Path | None:
    """``libmkl_rt`` of the installed ``mkl`` distribution (pip's wheel puts it in the
    environment's ``lib/``), else of the environment (conda's MKL), or None."""
    candidates: list[Path] = []
    try:
        files = importlib.metadata.distribution("mkl").files or []
        dist = importlib.metadata.distribution("mkl")
        candidates += [Path(dist.locate_file(f)) for f in files if Path(str(f)).name.startswith("libmkl_rt.so")]
    except importlib.metadata.PackageNotFoundError:
        pass
    candidates += sorted(Path(sys.prefix, "lib").glob("libmkl_rt.so*"))
    return next((p.resolve() for p in candidates if p.is_file()), None)


@compiled()
def _configure_mkl():
    """MKL's sequential threading layer and LP64 interface; returns what MKL reports as set."""
    return _set_threading_layer(MKL_THREADING_SEQUENTIAL), _set_interface_layer(MKL_INTERFACE_LP64)


@functools.cache
def cblas_available() -> bool:
    """Whether :class:`Cblas` runs here: ``libmkl_rt`` found and loaded, and MKL took the
    sequential threading layer and the LP64 interface (another library in the process may
    have set MKL up otherwise first: then :class:`NumpyDot`)."""
    path = mkl_library()
    if path is None:
        return False
    try:
        import llvmlite.binding

        llvmlite.binding.load_library_permanently(str(path))
        threading, interface = _configure_mkl()
    except Exception as exc:  # a broken or foreign MKL: the other route, never a failed start
        log.warning("MKL at %s does not load (%s): the compiled loops use SciPy's BLAS", path, exc)
        return False
    if threading != MKL_THREADING_SEQUENTIAL or interface != MKL_INTERFACE_LP64:
        log.warning("MKL at %s was set up with threading layer %d, interface %d by another library: the "
                    "compiled loops use SciPy's BLAS", path, threading, interface)
        return False
    return True


def route() -> NumpyDot | Cblas:
    """The route the compiled loops take in this process: :class:`Cblas` where it runs
    (:func:`cblas_available`), else :class:`NumpyDot`."""
    return Cblas() if cblas_available() else NumpyDot()


@intrinsic
def data_pointer(typingctx, arr):
    """An array's data pointer (``void *``) for an external call."""
    def codegen(context, builder, signature, args):
        ary = context.make_array(arr)(context, builder, args[0])
        return builder.bitcast(ary.data, cgutils.voidptr_t)

    return types.voidptr(arr), codegen


def gemm(blas, a, b, c):
    """``c = a @ b`` for C-ordered float32 matrices (rows may be strided: a slice of rows of a
    wider array) by ``blas``'s route; compiled code only."""
    raise NotImplementedError("blas.gemm runs inside compiled code")


def route_is(blas, cls) -> bool:
    return isinstance(blas, types.BaseNamedTuple) and blas.instance_class is cls


@overload(gemm)
def _gemm(blas, a, b, c):
    if route_is(blas, NumpyDot):
        def dot(blas, a, b, c):
            np.dot(a, b, c)

        return dot
    if route_is(blas, Cblas):
        if not all(isinstance(x, types.Array) and x.dtype == types.float32 and x.ndim == 2 for x in (a, b, c)):
            raise TypingError("blas.gemm: Cblas takes 2-D float32 arrays")

        def sgemm(blas, a, b, c):
            m, k, n = a.shape[0], a.shape[1], b.shape[1]
            if b.shape[0] != k or c.shape[0] != m or c.shape[1] != n:
                raise ValueError("blas.gemm: shapes do not match")
            if m == 0 or n == 0:
                return
            if a.strides[1] != 4 or b.strides[1] != 4 or c.strides[1] != 4:
                raise ValueError("blas.gemm: rows must be contiguous")
            _cblas_sgemm(CBLAS_ROW_MAJOR, CBLAS_NO_TRANS, CBLAS_NO_TRANS, m, n, k, np.float32(1.0), data_pointer(a),
                         max(a.strides[0] // 4, k, 1), data_pointer(b), max(b.strides[0] // 4, n, 1), np.float32(0.0),
                         data_pointer(c), max(c.strides[0] // 4, n, 1))

        return sgemm
    return None
