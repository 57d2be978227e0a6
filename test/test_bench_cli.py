"""``pcc bench``'s own checks: options refused before any timing starts."""

from __future__ import annotations

import pytest

from pcc_ros.cli.main import main


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
    assert main(["bench", "complete", "--backends", backends]) == 1
    assert said in caplog.text and "mirror" in caplog.text.split(said, 1)[1]
