"""The compiled loops' two BLAS routes (``pcc_ros.models.blas``): selection by what loads, the
same values both ways, and each route's kernels cached apart from the other's."""

from __future__ import annotations

import platform

import numpy as np
import pytest
from numba import njit

from pcc_ros.models import blas

needs_mkl = pytest.mark.skipif(not blas.cblas_available(),
                               reason="MKL's libmkl_rt (the mkl wheel, x86-64) is not installed here")


@njit
def _product(route, a, b, c):
    blas.gemm(route, a, b, c)


def _routes():
    return [blas.NumpyDot()] + ([blas.Cblas()] if blas.cblas_available() else [])


@pytest.mark.parametrize("m, k, n", [(0, 4, 3), (1, 3, 5), (7, 16, 32), (300, 64, 128), (5, 1, 1)])
def test_every_route_computes_the_product(m, k, n):
    rng = np.random.default_rng(m + k + n)
    a, b = rng.normal(size=(m, k)).astype(np.float32), rng.normal(size=(k, n)).astype(np.float32)
    for route in _routes():
        c = np.full((m, n), np.nan, np.float32)
        _product(route, a, b, c)
        np.testing.assert_allclose(c, a.astype(np.float64) @ b, rtol=1e-5, atol=1e-5, err_msg=str(route))


@needs_mkl
def test_cblas_writes_rows_of_a_wider_buffer_and_refuses_mismatched_shapes():
    """The kernels hand row slices of their work memory: only those rows are written."""
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(6, 8)).astype(np.float32), rng.normal(size=(8, 4)).astype(np.float32)
    c = np.zeros((10, 4), np.float32)
    _product(blas.Cblas(), a[:3], b, c[:3])
    np.testing.assert_allclose(c[:3], a[:3] @ b, rtol=1e-5, atol=1e-5)
    assert not c[3:].any()
    with pytest.raises(ValueError, match="shapes do not match"):
        _product(blas.Cblas(), a, b, c)


def test_without_mkl_the_route_is_numpy_dot(monkeypatch):
    monkeypatch.setattr(blas, "mkl_library", lambda: None)
    assert blas.cblas_available.__wrapped__() is False
    monkeypatch.setattr(blas, "cblas_available", lambda: False)
    assert type(blas.route()) is blas.NumpyDot


@pytest.mark.skipif(platform.machine() not in ("x86_64", "AMD64") or blas.mkl_library() is None,
                    reason="requirements.txt installs MKL on x86-64 only; not installed here")
def test_where_mkl_is_installed_the_compiled_loops_take_it():
    assert blas.cblas_available()
    assert type(blas.route()) is blas.Cblas


@needs_mkl
def test_shipped_pointpncnet_gives_the_same_completions_with_mkl_present_and_absent(monkeypatch):
    """Selection by capability, both ways: the whole compiled network on MKL and, with MKL
    taken away, on SciPy's BLAS; the same completions within float rounding."""
    from pcc_ros.models import default_checkpoint, load_completer

    path = default_checkpoint("pointpncnet")
    if path is None:
        pytest.skip("no shipped PointPnCNet weights")
    completer = load_completer("pointpncnet", path, device="cpu", batch_size=8)
    rng = np.random.default_rng(1)
    clouds = [(rng.normal(size=(int(n), 3)) * [0.5, 0.2, 0.15]).astype(np.float32) for n in (40, 300, 512, 7)]
    used = []
    infer = blas.route

    def recording():
        used.append(infer())
        return used[-1]

    monkeypatch.setattr(blas, "route", recording)
    with_mkl = completer.complete(clouds)
    monkeypatch.setattr(blas, "cblas_available", lambda: False)
    without = completer.complete(clouds)
    assert type(used[0]) is blas.Cblas and type(used[-1]) is blas.NumpyDot  # (empty tuples: all ==)
    for x, y in zip(with_mkl, without):
        np.testing.assert_allclose(x, y, rtol=0, atol=1e-5)


def test_kernel_cache_folder_follows_the_files_its_kernels_compile_from(tmp_path):
    """kernels.py's cache folder changes when blas.py (its gemm overloads) changes."""
    from pcc_ros import jit

    module, dependency = tmp_path / "k.py", tmp_path / "dep.py"
    module.write_text("x = 1\n")
    dependency.write_text("y = 1\n")
    before = jit._source_key.__wrapped__(str(module), ("dep.py",))
    assert before != jit._source_key.__wrapped__(str(module))
    dependency.write_text("y = 2\n")
    assert jit._source_key.__wrapped__(str(module), ("dep.py",)) != before
