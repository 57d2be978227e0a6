"""``pcc calibrate-filter`` across simulated sensors: small generated data, a YAML the pipeline
loads, the same file from the same seed, cross-validation by sensor and sequence, ablation."""

from __future__ import annotations

import json

import numpy as np

from pcc_ros.cli.main import main
from pcc_ros.pipeline.core import PipelineConfig
from pcc_ros.pipeline.filter import TERMS
from pcc_ros.workflows.filter_sensors import Rows, calibrate_sensors


def test_sensor_path_needs_no_labelled_frames_and_reproduces(tmp_path):
    args = ["calibrate-filter", "--sensor", "vlp16", "--sim-root", str(tmp_path / "sim"), "--sim-sequences", "2",
            "--sim-frames", "2", "--terms", "density,free_space,ground_gap", "--max-lost", "0.05"]
    assert main([*args, "--out", str(tmp_path / "a.yaml"), "--json", str(tmp_path / "a.json")]) == 0
    assert main([*args, "--out", str(tmp_path / "b.yaml")]) == 0  # the cached set, the same fit
    def body(name):  # the header names the --out path
        return [line for line in (tmp_path / name).read_text().splitlines() if "--out" not in line]

    assert body("a.yaml") == body("b.yaml")
    config = PipelineConfig.from_yaml(tmp_path / "a.yaml")
    assert config.filter.sensor == "vlp16" and config.filter.w_score == 0.0 and config.filter.w_mismatch == 0.0
    report = json.loads((tmp_path / "a.json").read_text())
    assert report["sensors"] == ["vlp16"] and set(report["ablation"]) == {"density", "free_space", "ground_gap"}
    assert report["rows"]["vlp16"]["false"] > 0 and len(report["cv_by_sequence"]["folds"]) == 2
    assert abs(report["weights"]["density"] - config.filter.w_density) < 1e-4


def test_one_rule_across_sensors_cross_validates_by_sensor():
    """Two synthetic 'sensors' whose rows follow one logistic law: the by-sensor folds find it."""
    rng = np.random.default_rng(0)
    parts = []
    for sensor in ("a", "b", "c"):
        n = 300
        x = np.zeros((n, len(TERMS)))
        x[:, 0] = rng.normal(0, 1, n)
        x[:, 1] = rng.normal(0, 1, n)
        false = rng.random(n) < 1 / (1 + np.exp(-(3 * x[:, 1] - 2 * x[:, 0])))
        kind = np.where(false, np.where(rng.random(n) < 0.5, "ghost", "confusion"), "true").astype(object)
        group = np.array([f"{sensor}:{i % 2}" for i in range(n)], dtype=object)
        parts.append(Rows(x, false, kind, np.full(n, sensor, dtype=object), group))
    result = calibrate_sensors(Rows.concatenate(parts), ("density", "free_space"), max_lost=0.05)
    assert set(result["cv_by_sensor"]["folds"]) == {"a", "b", "c"}
    assert result["weights"]["density"] < -1 and result["weights"]["free_space"] > 1.5
    assert result["cv_by_sensor"]["pooled"]["auc_false_above_true"] > 0.85
    assert result["ablation"]["free_space"]["auc_change"] > 0.05  # removing a real term costs
    assert set(result["cv_by_sequence"]["pooled"]["per_kind"]) == {"ghost", "confusion"}
    # each term alone: free_space (+3 in the law) ranks false high, density (-2) low; the
    # unmeasured (constant) columns are left out
    alone = result["term_auc"]
    assert set(alone) == {"density", "free_space"} and set(alone["free_space"]) == {"ghost", "confusion"}
    assert alone["free_space"]["ghost"] > 0.75 and alone["density"]["confusion"] < 0.35
