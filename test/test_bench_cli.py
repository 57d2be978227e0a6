"""``pcc bench``'s own checks: options refused before any timing starts."""

from __future__ import annotations

import pytest
from conftest import assert_named_failure, run_cli


@pytest.mark.parametrize(("backends", "said"), [
    ("mirror,foo", "unknown completion backend 'foo'; available: "),
    ("mirror,mirror", "--backends lists a backend twice"),
])
def test_bench_complete_refuses_named_backends_before_timing(backends, said, monkeypatch, caplog):
    """`--backends` used to be read at section 4, after minutes of timing, and an unknown name was
    then one table row's "error"; now the one-line error names the available backends first."""
    from pcc_ros.cli.bench import benchmarks_package

    benchmarks_package()
    import benchmarks.complete as complete

    def timing_started(*args, **kwargs):
        raise AssertionError("the benchmark started timing before --backends was checked")

    monkeypatch.setattr(complete, "_load_pointpncnet", timing_started)
    rc, text = run_cli(["bench", "complete", "--backends", backends], caplog)
    assert_named_failure(rc, text, said)
    assert "mirror" in text.split(said, 1)[1]


def test_backend_names_strip_check_and_allow_an_empty_none_where_asked():
    """One parse of a backends option for every command: names stripped, each checked, a name
    twice refused; ``""`` is an error unless the option means "none" by it (``empty_ok``)."""
    from pcc_ros.errors import ConfigError
    from pcc_ros.models import backend_names

    assert backend_names(" input , mirror ") == ["input", "mirror"]
    assert backend_names(" , ", empty_ok=True) == []
    with pytest.raises(ConfigError, match="--baselines is empty"):
        backend_names("", "--baselines")
    with pytest.raises(ConfigError, match="unknown completion backend 'nope'"):
        backend_names("input,nope", empty_ok=True)


def test_the_benchmarks_libtorch_route_compiles_outside_the_kernel_cache():
    """A cache index naming the benchmark-only route type could not be read by a node (it cannot
    import ``benchmarks``): the reference kernels compile with every kernel's disk cache off,
    and the caches are back after."""
    from numba.core.caching import NullCache
    from numba.core.dispatcher import Dispatcher

    from pcc_ros.cli.bench import benchmarks_package
    from pcc_ros.models import kernels

    benchmarks_package()
    from benchmarks import _reference_blas

    dispatchers = [d for d in vars(kernels).values() if isinstance(d, Dispatcher)]
    before = [d._cache for d in dispatchers]
    assert any(not isinstance(c, NullCache) for c in before)  # the package's kernels cache on disk
    with _reference_blas.uncached(kernels):
        assert all(isinstance(d._cache, NullCache) for d in dispatchers)
    assert [d._cache for d in dispatchers] == before
