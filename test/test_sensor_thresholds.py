"""Per-sensor reject thresholds: the ``sensor_thresholds`` parameter (parsed, refused when
malformed, written and read back), the preset a beam model matches, the threshold the filter's
decision uses, and the calibration step (``pcc calibrate-filter --sensor-thresholds``)."""

from __future__ import annotations

import json
import logging
import re
from dataclasses import replace

import numpy as np
import pytest

from pcc_ros.cli.main import main
from pcc_ros.errors import ConfigError
from pcc_ros.geometry.beams import SENSOR_PRESETS, SensorModel
from pcc_ros.pipeline.beam_model import MATCH_DEG, BeamModel, matching_preset, ringless_view, same_layout
from pcc_ros.pipeline.config import PipelineConfig
from pcc_ros.pipeline.core import Pipeline
from pcc_ros.pipeline.filter import FilterConfig, format_sensor_thresholds, parse_sensor_thresholds
from pcc_ros.types import Boxes
from pcc_ros.workflows.detection_eval import default_config
from pcc_ros.workflows.filter_calibration import preset_yaml
from pcc_ros.workflows.sensor_thresholds import fallback_threshold, sensor_threshold


def test_parse_and_format_sensor_thresholds():
    table = parse_sensor_thresholds(" hdl64:0.53, vlp16:0.46 ,")
    assert table == {"hdl64": 0.53, "vlp16": 0.46} and parse_sensor_thresholds("") == {}
    assert parse_sensor_thresholds(format_sensor_thresholds(table)) == table
    for bad, message in (("hdl64=0.5", "bad entry 'hdl64=0.5'; expected 'sensor:threshold'"),
                         ("vlp16:x", "bad entry 'vlp16:x'"), ("vlp16:1.0", "bad entry 'vlp16:1.0'"),
                         ("vlp16:0", "bad entry 'vlp16:0'"), (":0.5", "bad entry ':0.5'"),
                         ("hdl65:0.5", "bad entry 'hdl65:0.5'; unknown name 'hdl65'")):
        with pytest.raises(ConfigError, match=re.escape(f"sensor_thresholds: {message}")):
            parse_sensor_thresholds(bad)
    with pytest.raises(ConfigError, match=re.escape("sensor_thresholds: bad entry 'pandar:0.5'")):
        FilterConfig(sensor_thresholds="hdl64:0.5, pandar:0.5")  # refused when configured, not per frame
    config = FilterConfig(sensor_thresholds="vlp16:0.4", reject_threshold=0.7)
    assert config.threshold_for("vlp16") == 0.4
    assert config.threshold_for("hdl64") == 0.7 and config.threshold_for(None) == 0.7  # no entry / no match


def test_each_preset_matches_itself_and_no_other():
    for name, preset in SENSOR_PRESETS.items():
        assert matching_preset(preset) == name
        # a ring-less estimate sees the beams that return beyond a few metres: part of the table
        low = preset.elevations_deg[len(preset.elevations_deg) // 5]
        view = ringless_view(preset, low, 90.0)
        assert matching_preset(view) == name
        # ... one beam short of it (too few returns), each off by up to 0.2 deg (a real unit's calibration)
        rng = np.random.default_rng(len(name))
        kept = np.delete(np.asarray(view.elevations_deg), view.rings // 2)
        assert matching_preset(SensorModel(tuple(kept + rng.uniform(-0.2, 0.2, len(kept))),
                                           view.azimuth_resolution_deg)) == name
    # presets of one beam count differ by far more than the match tolerance
    for a, pa in SENSOR_PRESETS.items():
        for b, pb in SENSOR_PRESETS.items():
            if a != b:
                assert not same_layout(pa, pb, MATCH_DEG, 0.1)
    # two VLP-32C firing along one elevation read as one at half the step: the pair, not one unit
    pair = ringless_view(SENSOR_PRESETS["vlp32c_x2"], -16.0, 16.0)
    assert pair.rings == 31 and matching_preset(pair) == "vlp32c_x2"
    assert matching_preset(replace(pair, azimuth_resolution_deg=0.2)) == "vlp32c"


def test_random_ringless_views_match_their_own_preset_or_none():
    """A ring-less estimate: the beams past a random low cut, up to 10 % of them missing, each up to
    0.45 deg off, the step up to 5 % off. It may match nothing (then the lenient fallback applies);
    it must never match another preset (whose threshold was set for another sensor's cars)."""
    rng = np.random.default_rng(0)
    matched = 0
    for name, preset in SENSOR_PRESETS.items():
        el = np.asarray(preset.elevations_deg)
        for _ in range(60):
            view = ringless_view(preset, el[rng.integers(0, len(el) // 3)], 90.0)
            e = np.asarray(view.elevations_deg)
            e = e[rng.random(len(e)) >= rng.uniform(0, 0.1)]
            e = np.sort(e + rng.uniform(-0.45, 0.45, len(e)))
            step = view.azimuth_resolution_deg * rng.uniform(0.95, 1.05)
            found = matching_preset(SensorModel(tuple(e), step))
            assert found in (name, None), (name, found)
            matched += found == name
    assert matched >= 0.9 * 60 * len(SENSOR_PRESETS)


def test_a_made_up_layout_matches_nothing_and_the_fallback_applies(caplog):
    made_up = SensorModel(tuple(np.linspace(-20.0, 12.0, 40)), 0.25, "made-up")
    assert matching_preset(made_up) is None
    shifted = SensorModel(tuple(np.asarray(SENSOR_PRESETS["vlp16"].elevations_deg) + 1.0), 0.2)
    assert matching_preset(shifted) is None  # each beam 1 deg off the datasheet
    assert matching_preset(replace(SENSOR_PRESETS["vlp16"], azimuth_resolution_deg=0.4)) is None
    model = BeamModel("auto")
    model.model, model.preset = made_up, matching_preset(made_up)
    assert model.preset is None
    assert BeamModel("vlp16").preset == "vlp16" and BeamModel("auto").preset is None
    # the node then says which threshold judges it and how to set one for this sensor
    base = PipelineConfig(backend="input")
    pipeline = Pipeline(replace(base, filter=replace(base.filter, sensor_thresholds="hdl64:0.5", reject_threshold=0.7)))
    pipeline.beam_model = model
    with caplog.at_level(logging.INFO, logger="pcc_ros.pipeline.core"):
        assert pipeline.reject_threshold() == 0.7
    assert "matches no preset" in caplog.text and "pcc calibrate-filter --sensor-from" in caplog.text


def _street(height: float = 1.73):
    """A flat ground scan of a VLP-16 ``height`` metres high (every ring, the whole revolution)
    and car boxes on the ground."""
    vlp16 = SENSOR_PRESETS["vlp16"]
    el = np.deg2rad(np.asarray(vlp16.elevations_deg))[:, None]
    az = np.deg2rad(np.arange(0.0, 360.0, vlp16.azimuth_resolution_deg))[None, :]
    down = el < 0
    r = np.where(down, height / np.sin(-np.where(down, el, -1.0)), 40.0)  # slant range to the ground, else a wall
    r = np.minimum(r, 60.0 / np.cos(el))
    pts = np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el) + 0 * az], -1)
    z = 0.75 - height
    boxes = Boxes(np.array([[12.0, 3.0, z], [20.0, -6.0, z], [30.0, 8.0, z]]),
                  np.tile([[4.2, 1.8, 1.5]], (3, 1)), np.zeros(3), ["Car"] * 3, np.full(3, 0.8))
    return pts.reshape(-1, 3).astype(np.float32), boxes


def test_the_filter_decision_uses_the_matched_presets_threshold(caplog):
    points, boxes = _street()
    base = PipelineConfig(backend="input")
    for table, expected in (("vlp16:0.000001", "rejected"), ("vlp16:0.999999", "kept")):
        for sensor in ("vlp16", "auto"):  # named, and estimated from the scan (then matched)
            config = replace(base, filter=replace(base.filter, sensor=sensor, sensor_thresholds=table,
                                                  reject_threshold=0.5))
            pipeline = Pipeline(config)
            with caplog.at_level(logging.INFO, logger="pcc_ros.pipeline.core"):
                result = pipeline.process(points, boxes)
            assert pipeline.beam_model.preset == "vlp16"
            assert list(result.status) == [expected] * len(boxes), (table, sensor)
            assert pipeline.threshold_in_force == ("vlp16", parse_sensor_thresholds(table)["vlp16"])
    assert "reject threshold 1.0000, the vlp16 entry of sensor_thresholds" in caplog.text
    # no entry for the matched preset: reject_threshold, said once (not every frame)
    config = replace(base, filter=replace(base.filter, sensor="vlp16", sensor_thresholds="hdl64:0.000001",
                                          reject_threshold=0.999999))
    pipeline = Pipeline(config)
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="pcc_ros.pipeline.core"):
        for _ in range(3):
            assert set(pipeline.process(points, boxes).status) == {"kept"}
    assert caplog.text.count("reject threshold") == 1 and "no entry for vlp16" in caplog.text
    # before the first beam estimate (a scan without beam structure): reject_threshold
    noise = np.random.default_rng(0).uniform(-30, 30, (3000, 3)).astype(np.float32)
    config = replace(base, filter=replace(base.filter, sensor="auto", sensor_thresholds="hdl64:0.000001",
                                          reject_threshold=0.999999))
    pipeline = Pipeline(config)
    assert set(pipeline.process(noise, boxes).status) == {"kept"}
    assert pipeline.threshold_in_force == (None, 0.999999)


def test_sensor_threshold_is_chosen_by_cross_validation_over_folds():
    rng = np.random.default_rng(3)
    n = 4000
    false = rng.random(n) < 0.2
    p = np.where(false, rng.beta(5, 2, n), rng.beta(2, 5, n))
    group = np.array([f"x:{i % 8:04d}" for i in range(n)], dtype=object)
    result = sensor_threshold(p, false, group, target_lost=0.02, per_fold=2)
    assert result["folds"] == 4 and result["sequences_per_fold"] == 2
    worst = np.asarray(result["held_out_worst_fold"])
    chosen = result["grid"].index(result["budget"])
    assert worst[chosen] <= 0.02
    assert all(worst[i] > 0.02 for i in range(chosen + 1, len(worst)))  # the largest budget within the target
    assert result["in_sample_lost"] <= result["budget"] + 1e-9
    with pytest.raises(ConfigError, match="no budget keeps every held-out fold"):
        sensor_threshold(p, false, group, target_lost=0.0001)
    with pytest.raises(ConfigError, match="two or more folds"):
        sensor_threshold(p, false, np.full(n, "x:0000", dtype=object))
    assert fallback_threshold({"a": {"threshold": 0.4}, "b": {"threshold": 0.6}}, 0.5) == 0.6


def test_yaml_round_trip_keeps_the_table(tmp_path):
    table = {"hdl64": 0.5313, "vlp16": 0.4584}
    text = preset_yaml(default_config(), 1.0, FilterConfig().weights, 0.6,
                       {"sensor_thresholds": format_sensor_thresholds(table)}, "# calibrated: test\n")
    path = tmp_path / "f.yaml"
    path.write_text(text)
    config = PipelineConfig.from_yaml(path).filter
    assert parse_sensor_thresholds(config.sensor_thresholds) == table and config.reject_threshold == 0.6
    assert config.threshold_for("vlp16") == 0.4584 and config.threshold_for("os1_64") == 0.6


def test_cli_sensor_thresholds_on_the_weights_of_a_yaml(tmp_path):
    """The per-sensor step alone, on the shipped weights: the table in the YAML and its header,
    the weights and every other line as they were; the cached rows make the rerun identical."""
    args = ["calibrate-filter", "--sensor-thresholds", "vlp16,hdl32", "--sim-root", str(tmp_path / "sim"),
            "--sim-sequences", "2", "--sim-frames", "2", "--threshold-folds", "1", "--target-lost", "0.5",
            "--rows-cache", str(tmp_path / "rows"), "--weights-from", str(default_config())]
    assert main([*args, "--out", str(tmp_path / "a.yaml"), "--json", str(tmp_path / "a.json")]) == 0
    assert len(list((tmp_path / "rows").glob("rows_*.npz"))) == 2
    assert main([*args, "--out", str(tmp_path / "b.yaml")]) == 0
    a, b = (tmp_path / "a.yaml").read_text(), (tmp_path / "b.yaml").read_text()
    assert a == b
    report = json.loads((tmp_path / "a.json").read_text())["sensor_thresholds"]
    config = PipelineConfig.from_yaml(tmp_path / "a.yaml").filter
    shipped = PipelineConfig.from_yaml(default_config()).filter
    table = parse_sensor_thresholds(config.sensor_thresholds)
    assert set(table) == {"vlp16", "hdl32"}
    for layout, t in report["layouts"].items():
        assert table[layout] == pytest.approx(t["threshold"], abs=1e-4) and t["budget"] in t["grid"]
    assert config.reject_threshold == pytest.approx(max([*table.values(), shipped.reject_threshold]), abs=1e-4)
    assert np.allclose(config.weights, shipped.weights) and config.w_bias == shipped.w_bias
    header = [line for line in a.splitlines() if line.startswith("# calibrated:")]
    assert any("--sim-sensors" in line for line in header)  # the weights' provenance kept
    assert any("sensor_thresholds per layout" in line for line in header)
    assert main(["calibrate-filter", "--sensor-thresholds", "vlp17", "--sim-root", str(tmp_path / "sim")]) != 0


def test_a_sensor_mounted_far_from_the_presets_height_is_warned_about(caplog):
    """The presets' thresholds were set 1.73 m high: a VLP-16 on a small robot (0.8 m) matches
    the vlp16 preset and keeps its entry (a more lenient threshold still lost over 2 % of such a
    street's cars), and the log says how to set one for it; at 1.73 m and 1.5 m no warning."""
    base = PipelineConfig(backend="input")
    config = replace(base, filter=replace(base.filter, sensor="auto", sensor_thresholds="vlp16:0.3",
                                          reject_threshold=0.9))
    for height, warned in ((1.73, False), (1.5, False), (0.8, True)):
        points, boxes = _street(height)
        pipeline = Pipeline(config)
        caplog.clear()
        with caplog.at_level(logging.INFO, logger="pcc_ros.pipeline.core"):
            pipeline.process(points, boxes)
        assert pipeline.beam_model.preset == "vlp16" and pipeline.threshold_in_force == ("vlp16", 0.3)
        assert pipeline.beam_model.mount_height == pytest.approx(height, abs=0.05)
        assert ("sits 0.80 m above the ground" in caplog.text and "--sensor-from" in caplog.text) == warned, height
    named = Pipeline(replace(config, filter=replace(config.filter, sensor="vlp16")))
    named.process(*_street(0.8))
    assert named.beam_model.mount_height is None  # a named preset is taken as named
