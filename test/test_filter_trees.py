"""Boosted trees over the evidence terms: the vectorised traversal, the file, the fit, the rule."""

from __future__ import annotations

import json
import re
from dataclasses import replace

import numpy as np
import pytest
from fuzz_support import RANDOM_JSON_BYTES
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pcc_ros.errors import ConfigError
from pcc_ros.pipeline.filter import TERMS, FilterConfig, rule_probability, whole_rule
from pcc_ros.pipeline.trees import SHIPPED_PATH, TermTrees, load_trees
from pcc_ros.workflows.boosting import boost
from pcc_ros.workflows.detection_eval import auc


def _random_trees(rng, t=7, depth=3, terms=("density", "depth", "cover")) -> TermTrees:
    inner = 2 ** depth - 1
    threshold = rng.normal(size=(t, inner))
    threshold[rng.random((t, inner)) < 0.2] = np.inf  # unsplit nodes send every row left
    return TermTrees(terms, rng.integers(0, len(terms), (t, inner)), threshold, rng.normal(size=(t, inner + 1)))


def _walk(trees: TermTrees, row: np.ndarray) -> float:
    """One row, one tree at a time: the definition the vectorised margin must equal."""
    total = 0.0
    inner = trees.feature.shape[1]
    for t in range(len(trees.leaf)):
        node = 0
        while node < inner:
            node = 2 * node + (2 if row[trees.feature[t, node]] > trees.threshold[t, node] else 1)
        total += trees.leaf[t, node - inner]
    return total


def test_margin_equals_walking_each_tree():
    rng = np.random.default_rng(0)
    trees = _random_trees(rng)
    x = rng.normal(size=(50, 3))
    x[3, 1] = np.nan  # a missing term reads 0, as in the weighted sum
    want = [_walk(trees, np.nan_to_num(r)) for r in x]
    np.testing.assert_allclose(trees.margin(x), want, rtol=0, atol=1e-12)
    assert trees.margin(np.zeros((0, 3))).shape == (0,)


def test_file_round_trip_and_bad_files(tmp_path):
    trees = replace(_random_trees(np.random.default_rng(1)), linear={"w_bias": 1.5}, provenance={"seed": 3})
    path = tmp_path / "t.json"
    trees.save(path)
    back = load_trees(path, TERMS)
    np.testing.assert_array_equal(back.threshold, trees.threshold)
    np.testing.assert_array_equal(back.leaf, trees.leaf)
    assert back.linear == {"w_bias": 1.5} and back.provenance == {"seed": 3}
    text = path.read_text()
    bad = {"truncated.json": text[: len(text) // 2], "other.json": json.dumps({"format": "x"}),
           "unknown.json": text.replace('"density"', '"colour"'),
           "shape.json": json.dumps({**json.loads(text), "leaf": [[0.0]]})}
    for name, body in bad.items():
        (tmp_path / name).write_text(body)
        with pytest.raises(ConfigError, match=re.escape(name)):
            load_trees(tmp_path / name, TERMS)
    with pytest.raises(ConfigError, match=r"missing\.json"):
        load_trees(tmp_path / "missing.json", TERMS)


def test_boost_learns_an_interaction_the_sum_cannot():
    """False iff exactly one of two terms is high: no weighted sum ranks that; depth-2 trees do."""
    rng = np.random.default_rng(2)
    x = rng.normal(size=(4000, 2))
    false = (x[:, 0] > 0) ^ (x[:, 1] > 0)
    fit = boost(x, false, np.ones(len(x)), np.zeros(len(x)), ("density", "depth"), depth=2, rounds=60, rate=0.2)
    p = fit.margin(x)
    assert auc(p, ~false) > 0.97
    assert auc(x @ np.array([1.0, 1.0]), ~false) < 0.6
    again = boost(x, false, np.ones(len(x)), np.zeros(len(x)), ("density", "depth"), depth=2, rounds=60, rate=0.2)
    np.testing.assert_array_equal(again.leaf, fit.leaf)  # no sampling: the same rows, the same trees


def test_boost_keeps_min_leaf_rows_and_starts_from_the_base():
    rng = np.random.default_rng(3)
    x = rng.normal(size=(600, 3))
    false = x[:, 0] + 0.3 * rng.normal(size=600) > 0.5
    fit = boost(x, false, np.ones(600), np.zeros(600), ("density", "depth", "cover"), depth=3, rounds=20,
                min_leaf=50)
    inner = fit.feature.shape[1]
    for t in range(len(fit.leaf)):
        node = np.zeros(600, dtype=int)
        for _ in range(fit.depth):
            node = 2 * node + 1 + (x[np.arange(600), fit.feature[t, node]] > fit.threshold[t, node])
        sizes = np.bincount(node - inner, minlength=inner + 1)
        assert ((sizes == 0) | (sizes >= 50)).all(), sizes
    # a base that already says everything leaves the trees (almost) nothing to add
    sure = np.where(false, 30.0, -30.0)
    assert np.abs(boost(x, false, np.ones(600), sure, ("density", "depth", "cover"), rounds=5).leaf).max() < 1e-6


def _trees_file(tmp_path, config: FilterConfig, leaf: float = 5.0):
    trees = TermTrees(("density",), np.zeros((1, 1), dtype=np.int64), np.array([[-1.0]]), np.array([[0.0, leaf]]),
                      linear={"w_bias": config.w_bias, **{f"w_{t}": float(w) for t, w in zip(TERMS, config.weights)}})
    path = tmp_path / "trees.json"
    trees.save(path)
    return path


def test_the_rule_adds_the_trees_to_its_own_weights_only(tmp_path):
    base = FilterConfig(trees="")
    path = _trees_file(tmp_path, base)
    with_trees = replace(base, trees=str(path))
    x = np.zeros((2, len(TERMS)))
    x[:, TERMS.index("density")] = [-2.0, 0.0]  # left of the split (+0), right of it (+5)
    z_plain = np.log(rule_probability(x, base) / (1 - rule_probability(x, base)))
    z_trees = np.log(rule_probability(x, with_trees) / (1 - rule_probability(x, with_trees)))
    np.testing.assert_allclose(z_trees - z_plain, [0.0, 5.0], atol=1e-9)
    assert "density" in with_trees.weighted_terms
    with pytest.raises(ConfigError, match="boosted from other filter weights"):
        replace(with_trees, w_density=1.0)
    with pytest.raises(ConfigError, match=r"nowhere\.json"):
        FilterConfig(trees=str(tmp_path / "nowhere.json"))
    assert FilterConfig().term_trees is not None  # the shipped rule adds the shipped trees
    # a parameter set naming its own weights but no trees gets none (the trees were not boosted from them)
    assert whole_rule({"w_density": 1.0})["trees"] == ""
    assert "trees" not in whole_rule({"reject_threshold": 0.4})


def test_cli_trees_out_boosts_from_the_kept_weights(tmp_path):
    """``--trees-out``: the trees file (boosted from the shipped weights, with its provenance), the
    YAML naming it with each layout's threshold; the same command writes the same files again."""
    from pcc_ros.cli.main import main
    from pcc_ros.pipeline.config import PipelineConfig
    from pcc_ros.pipeline.filter import parse_sensor_thresholds
    from pcc_ros.workflows.detection_eval import default_config

    args = ["calibrate-filter", "--sensor-thresholds", "vlp16,hdl32", "--sim-root", str(tmp_path / "sim"),
            "--sim-sequences", "2", "--sim-frames", "3", "--threshold-folds", "1", "--target-lost", "0.5",
            "--rows-cache", str(tmp_path / "rows"), "--weights-from", str(default_config()), "--tree-rounds", "4"]
    for name in ("a", "b"):
        assert main([*args, "--trees-out", str(tmp_path / f"{name}.json"), "--out", str(tmp_path / f"{name}.yaml"),
                     "--json", str(tmp_path / f"{name}_report.json")]) == 0
    config = PipelineConfig.from_yaml(tmp_path / "a.yaml").filter
    shipped = PipelineConfig.from_yaml(default_config()).filter
    assert config.trees == str(tmp_path / "a.json")
    trees = config.term_trees
    assert trees is not None and len(trees.leaf) == 4 and trees.provenance["rows"].keys() == {"vlp16", "hdl32"}
    assert np.allclose(config.weights, shipped.weights) and config.w_bias == shipped.w_bias
    assert set(parse_sensor_thresholds(config.sensor_thresholds)) == {"vlp16", "hdl32"}
    again = load_trees(tmp_path / "b.json", TERMS)
    np.testing.assert_array_equal(again.leaf, trees.leaf)
    report = json.loads((tmp_path / "a_report.json").read_text())
    assert report["by_sequence"]["folds"] == 2 and "with_trees" in report["by_sequence"]
    header = [line for line in (tmp_path / "a.yaml").read_text().splitlines() if line.startswith("# calibrated:")]
    assert any(line.startswith("# calibrated: trees: pcc calibrate-filter --trees-out") for line in header)
    assert main(["calibrate-filter", "--trees-out", str(tmp_path / "c.json"), "--sim-root", str(tmp_path / "sim")]) != 0


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=RANDOM_JSON_BYTES)
def test_random_bytes_are_a_config_error_naming_the_file(tmp_path, data):
    path = tmp_path / "random_trees.json"
    path.write_bytes(data)
    with pytest.raises(ConfigError, match=r"random_trees\.json"):
        load_trees(path, TERMS)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(position=st.floats(0, 1, exclude_max=True), byte=st.integers(0, 255), cut=st.booleans())
def test_damaged_shipped_trees_are_refused_or_read_whole(tmp_path, position, byte, cut):
    """A cut or one changed byte of the shipped file: a ConfigError naming it, or (a digit changed
    into another) trees of the same shape; never another exception."""
    data = bytearray(SHIPPED_PATH.read_bytes())
    at = int(position * len(data))
    data = data[:at] if cut else data[:at] + bytes([byte]) + data[at + 1:]
    path = tmp_path / "damaged.json"
    path.write_bytes(bytes(data))
    try:
        trees = load_trees(path, TERMS)
    except ConfigError as exc:
        assert "damaged.json" in str(exc)
    else:
        assert trees.leaf.shape == load_trees(SHIPPED_PATH, TERMS).leaf.shape


def test_a_corrupt_trees_file_is_a_named_failure_of_the_command(tmp_path, caplog):
    from conftest import assert_named_failure, run_cli

    (tmp_path / "trees.json").write_text('{"format": "pcc_ros.filter_trees/1", "terms": ["density"], "feature": [[0')
    config = tmp_path / "filter.yaml"
    config.write_text("/**:\n  ros__parameters:\n    trees: " + str(tmp_path / "trees.json") + "\n")
    rc, text = run_cli(["eval", "detections", "--nuscenes", "nowhere", "--config", config,
                        "--json", tmp_path / "out.json"], caplog)
    assert_named_failure(rc, text, str(tmp_path / "trees.json"), output=tmp_path / "out.json")


def test_a_fresh_fit_with_thresholds_writes_no_trees(tmp_path):
    """``--sim-sensors ... --sensor-thresholds``: new weights, their own thresholds, and ``trees: ""``
    (the shipped trees were boosted from the shipped weights, not these)."""
    from pcc_ros.cli.main import main
    from pcc_ros.pipeline.config import PipelineConfig

    out = tmp_path / "fit.yaml"
    assert main(["calibrate-filter", "--sim-sensors", "vlp16,hdl32", "--sensor-thresholds", "vlp16,hdl32",
                 "--sim-root", str(tmp_path / "sim"), "--sim-sequences", "2", "--sim-frames", "3",
                 "--threshold-folds", "1", "--target-lost", "0.5", "--max-lost", "0.05", "--folds", "0",
                 "--out", str(out)]) == 0
    config = PipelineConfig.from_yaml(out).filter
    assert config.trees == "" and config.term_trees is None and config.sensor_thresholds


def test_monotone_trees_never_bend_against_a_held_direction():
    """A false label that rises with term 0 except in a band where the data say the opposite: free
    trees follow the band, trees held to +1 on term 0 never lower the logit as term 0 grows."""
    rng = np.random.default_rng(5)
    x = rng.uniform(-1, 1, size=(3000, 2))
    p = 1 / (1 + np.exp(-4 * x[:, 0]))
    p[(x[:, 0] > 0.2) & (x[:, 0] < 0.5)] = 0.05  # the band that bends against the direction
    false = rng.random(3000) < p
    args = (x, false, np.ones(3000), np.zeros(3000), ("density", "depth"))
    free = boost(*args, depth=3, rounds=40, rate=0.3)
    held = boost(*args, depth=3, rounds=40, rate=0.3, monotone=(1, 0))
    grid = np.linspace(-1, 1, 201)
    for other in np.linspace(-1, 1, 9):
        probe = np.stack([grid, np.full_like(grid, other)], axis=1)
        assert (np.diff(held.margin(probe)) >= -1e-12).all()
    assert (np.diff(free.margin(np.stack([grid, np.zeros_like(grid)], axis=1))) < -1e-6).any()
    unconstrained = boost(*args, depth=3, rounds=40, rate=0.3, monotone=(0, 0))
    np.testing.assert_array_equal(unconstrained.leaf, free.leaf)  # all-zero constraints: the free fit
    with pytest.raises(ValueError, match="monotone"):
        boost(*args, monotone=(2, 0))
