"""`pcc demo` end to end (small, with a baseline backend so it needs no trained weights)."""

from __future__ import annotations

import json
import logging

import pytest
from conftest import assert_named_failure, run_cli

from pcc_ros.cli.main import main


@pytest.mark.slow
def test_demo_runs_end_to_end(tmp_path, shared_data, capsys, caplog):
    caplog.set_level(logging.INFO, logger="pcc_ros")
    out = tmp_path / "demo"
    code = main(["demo", "--out", str(out), "--backend", "mirror", "--baselines", "input", "--frames", "2",
                 "--kitti", str(shared_data / "kitti_tracking")])
    assert code == 0
    results = json.loads((out / "demo.json").read_text())
    rows = {r["backend"]: r for r in results["synthcars"]["completion"]}
    assert set(rows) == {"mirror", "input"} and rows["input"]["instances"] > 0
    # The mirror prior adds the unseen side: it covers the true shape better than the raw input.
    assert rows["mirror"]["coverage"] < rows["input"]["coverage"]
    synth_filter = results["synthcars"]["filter"]
    assert synth_filter["true_kept"] + synth_filter["true_rejected"] > 0
    assert results["kitti"]["filter"]["true_kept"] > 0
    for png in (out / "synthcars_demo.png", out / "kitti_demo.png"):
        assert png.stat().st_size > 10_000
    assert "SynthCars completion vs true shapes" in capsys.readouterr().out
    # the baseline is scored on its completions only: the completion node runs it (the log read as if
    # the filter node completed with `input`: "detection_filter_node: filter node ready: backend=input")
    ready = [r.getMessage() for r in caplog.records if "node ready" in r.getMessage()]
    assert sum("filter node ready: backend=mirror" in m for m in ready) == 2, ready  # SynthCars, KITTI
    assert sum("completion node ready: backend=input" in m for m in ready) == 1, ready
    assert not any("filter node ready: backend=input" in m for m in ready), ready


def test_demo_with_a_kitti_folder_that_is_not_there_fails_naming_it(tmp_path, caplog):
    """`--kitti PATH` asked for by name: a missing PATH is an error before any work, not a demo
    that quietly leaves out its real-data half and exits 0."""
    out = tmp_path / "demo"
    argv = ["demo", "--out", str(out), "--backend", "mirror", "--frames", "2", "--kitti", str(tmp_path / "nope")]
    assert_named_failure(*run_cli(argv, caplog), tmp_path / "nope", "no KITTI tracking data")
    assert not (out / "demo.json").exists()


@pytest.mark.parametrize("flag", [["--backend", "mirorr"], ["--baselines", "input,mirorr"]])
def test_demo_names_a_misspelt_backend_before_any_work(tmp_path, caplog, flag):
    """The backend and the baselines are checked first (was: after SynthCars was generated, and for
    a baseline after the backend's whole replay)."""
    out = tmp_path / "demo"
    rc, text = run_cli(["demo", "--out", str(out), "--frames", "2", *flag], caplog)
    assert_named_failure(rc, text, "unknown completion backend 'mirorr'; available: ")
    assert not out.exists()
