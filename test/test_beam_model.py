"""The filter's beam model from the data (``sensor: auto``): the preset table shared with the
simulator, the estimate from the ring field and from the scan alone on SynthCars scans of
several layouts, on the real nuScenes (ring field) and KITTI (none) frames, the keep /
re-check / fallback rules, and the ring read from a PointCloud2."""

from __future__ import annotations

import logging

import numpy as np
import pytest
from conftest import assert_named_failure, run_cli

from pcc_ros.errors import ConfigError
from pcc_ros.geometry.beams import SENSOR_PRESETS, SensorModel, sensor_preset
from pcc_ros.pipeline.beam_model import (
    MIN_BEAM_POINTS,
    MIN_RANGE,
    BeamModel,
    estimate_sensor,
    matching_preset,
    ring_column,
    same_layout,
    sensor_for,
)

pytest.importorskip("open3d")

#: Layouts simulated below: every preset (uniform, non-uniform (VLP-32C, Pandar64), two stacked units).
LAYOUTS = ("hdl64", "hdl32", "vlp16", "vlp32c", "os1_64", "os1_128", "pandar64", "vlp32c_x2")


def test_preset_table_is_the_datasheets():
    assert set(SENSOR_PRESETS) >= {"hdl64", "hdl32", "vlp16", "vlp32c", "vlp32c_x2", "os1_64", "os1_128", "pandar64"}
    for name, model in SENSOR_PRESETS.items():
        e = np.asarray(model.elevations_deg)
        assert np.all(np.diff(e) >= 0), name  # ascending
        assert model.name == name
    assert sensor_preset("hdl64").rings == 64 and sensor_preset("hdl32").rings == 32
    assert sensor_preset("vlp16").elevations_deg == tuple(np.arange(-15.0, 16.0, 2.0))
    vlp32c = np.diff(sensor_preset("vlp32c").elevations_deg)
    assert vlp32c.min() == pytest.approx(1 / 3, abs=2e-3) and vlp32c.max() > 9  # dense at the horizon only
    assert sensor_preset("vlp32c_x2").rings == 64
    assert sensor_preset("vlp32c_x2").elevations_deg[::2] == sensor_preset("vlp32c").elevations_deg
    assert sensor_preset("pandar64").rings == 64
    for name, rings in (("os1_64", 64), ("os1_128", 128)):
        model = sensor_preset(name)
        assert model.rings == rings and model.elevations_deg[0] == -22.5 and model.elevations_deg[-1] == 22.5
    with pytest.raises(ConfigError, match="unknown sensor 'hdl65'"):
        sensor_preset("hdl65")
    with pytest.raises(ConfigError, match="bad sensor model"):
        SensorModel((1.0,), 0.2)


def _simulated(layout: str):
    """One SynthCars frame of a short street seen by ``layout``, and the simulated sensor."""
    from pcc_ros.data.synthetic.generator import FRAME_STREAM, build_sequence, seeded_rng, simulate_frame
    from pcc_ros.data.synthetic.lidar import Sensor
    from pcc_ros.data.synthetic.scene import SceneParams

    street = build_sequence(5, 0, 1, "test", SceneParams(margin=40.0, cull_range=80.0))
    sensor = Sensor(layout=layout)
    return simulate_frame(street, 0, sensor, seeded_rng(5, 2, 0, FRAME_STREAM, 0)), sensor


@pytest.mark.parametrize("layout", LAYOUTS)
def test_estimate_matches_the_simulated_layout(layout):
    result, sensor = _simulated(layout)
    scan = result.scan
    assert sensor.model == SENSOR_PRESETS[layout]  # one definition, simulation and filter
    truth = np.sort(sensor.elevations)
    step = SENSOR_PRESETS[layout].azimuth_resolution_deg
    # With the ring field (the beam index of each return): every beam, exactly.
    ring = scan.ray // len(sensor.azimuths)
    found = estimate_sensor(scan.points, ring)
    assert found.rings == len(truth)
    np.testing.assert_allclose(found.elevations_deg, truth, atol=1e-3)
    assert found.azimuth_resolution_deg == pytest.approx(step, rel=0.01)
    # From the scan alone: every beam with returns beyond MIN_RANGE (a beam whose returns are
    # all nearer meets no box beyond it), each elevation once.
    r = np.linalg.norm(scan.points[:, :3], axis=1)
    counts = np.bincount(ring[r > MIN_RANGE], minlength=len(truth))
    observable = np.unique(np.round(sensor.elevations[counts >= MIN_BEAM_POINTS], 9))
    alone = estimate_sensor(scan.points)
    assert alone.rings == len(observable)
    np.testing.assert_allclose(alone.elevations_deg, observable, atol=1e-3)
    # Beams x columns is what the expected returns count: two units firing along one elevation
    # read as one beam at half the step.
    per_elevation = len(truth) / len(np.unique(np.round(truth, 9)))
    assert alone.azimuth_resolution_deg == pytest.approx(step / per_elevation, rel=0.06)
    # Both estimates are recognised as the preset (what sensor_thresholds keys on).
    assert matching_preset(found) == layout and matching_preset(alone) == layout


def test_real_nuscenes_ring_field_gives_the_hdl32(shared_data):
    from pcc_ros.data.nuscenes import FIELDS, read_pcd_bin

    scan = read_pcd_bin(next((shared_data / "nuscenes_mini" / "samples" / "LIDAR_TOP").glob("*.pcd.bin")))
    assert ring_column(scan[:, :4], FIELDS[:4]) is None
    found = estimate_sensor(scan[:, :3], ring_column(scan, FIELDS))
    hdl32 = SENSOR_PRESETS["hdl32"]
    assert found.rings == 32
    np.testing.assert_allclose(found.elevations_deg, hdl32.elevations_deg, atol=0.4)  # the unit's calibration
    assert found.azimuth_resolution_deg == pytest.approx(hdl32.azimuth_resolution_deg, rel=0.03)
    assert matching_preset(found) == "hdl32"  # the unit's calibration is within MATCH_DEG of the datasheet
    # without the ring field: the lasers' offsets smear each beam over several histogram
    # spikes; the returns per firing set the count back: beams x columns between -18 and 0 deg
    alone = estimate_sensor(scan[:, :3])
    assert _density(alone, -18.0) == pytest.approx(_density(hdl32, -18.0), rel=0.2)  # measured: +15 %
    assert matching_preset(alone) == "hdl32"  # its beams within MATCH_DEG_RINGLESS (up to 0.61 deg off)


def _density(model: SensorModel, low: float = -20.0) -> float:
    """Beams between ``low`` and 0 deg (where cars are seen) times columns per revolution."""
    e = np.asarray(model.elevations_deg)
    return ((e > low) & (e < 0)).sum() / model.azimuth_resolution_deg


def test_real_kitti_scan_without_ring_is_close_to_the_hdl64(shared_data):
    scan = np.fromfile(shared_data / "kitti_tracking" / "training" / "velodyne" / "0000" / "000000.bin",
                       np.float32).reshape(-1, 4)
    found = estimate_sensor(scan)
    hdl64 = SENSOR_PRESETS["hdl64"]
    assert 56 <= found.rings <= 66  # the steepest beams meet the ground within MIN_RANGE
    assert found.azimuth_resolution_deg == pytest.approx(hdl64.azimuth_resolution_deg, rel=0.05)
    # beams x columns between -20 and 0 deg (where cars are seen), within 10 % of the datasheet's
    assert _density(found) == pytest.approx(_density(hdl64), rel=0.1)
    assert matching_preset(found) == "hdl64"  # 59 beams within 0.21 deg of 63 the datasheet has over that span


def test_no_beam_structure_falls_back_and_an_estimate_is_kept_then_rechecked(caplog):
    rng = np.random.default_rng(0)
    noise = rng.uniform(-30, 30, (5000, 3))  # no beams: elevations spread evenly
    assert estimate_sensor(noise) is None
    assert estimate_sensor(noise[:10]) is None
    vlp16, _ = _simulated("vlp16")
    os1, _ = _simulated("os1_64")
    model = BeamModel("auto", recheck_every=3, retry_every=2)
    with caplog.at_level(logging.WARNING, logger="pcc_ros.pipeline.beam_model"):
        assert model.for_frame(noise) == SENSOR_PRESETS["hdl64"]
        assert not model.due()  # retried after retry_every frames
        assert model.for_frame(vlp16.scan.points) == SENSOR_PRESETS["hdl64"]
        assert model.due()
        first = model.for_frame(vlp16.scan.points)
    assert "no beam structure" in caplog.text and caplog.text.count("no beam structure") == 1
    assert first.rings == 16 and same_layout(first, SENSOR_PRESETS["vlp16"], tol_deg=1e-3, step_tol=0.01)
    # kept without re-estimating until the re-check, then re-adopted on drift (logged)
    assert model.for_frame(os1.scan.points) is first and model.for_frame(os1.scan.points) is first
    assert model.due()
    with caplog.at_level(logging.WARNING, logger="pcc_ros.pipeline.beam_model"):
        now = model.for_frame(os1.scan.points)
    assert model.drifts == 1 and "drifted" in caplog.text and now.rings > 16
    # a preset never estimates
    fixed = BeamModel("vlp16")
    assert not fixed.due() and fixed.for_frame(noise) is SENSOR_PRESETS["vlp16"]
    assert sensor_for("pandar64", noise) is SENSOR_PRESETS["pandar64"]
    assert sensor_for("auto", noise) is SENSOR_PRESETS["hdl64"]
    with pytest.raises(ConfigError, match="sensor must be"):
        BeamModel("lidar")


def test_pipeline_reads_the_ring_field_and_organized_rows_of_a_cloud():
    from pcc_ros.msg.detections import detection_array_from_boxes
    from pcc_ros.msg.pointcloud2 import create_cloud
    from pcc_ros.pipeline.config import PipelineConfig
    from pcc_ros.pipeline.core import Pipeline
    from pcc_ros.types import Boxes

    result, sensor = _simulated("vlp32c")
    scan = result.scan
    ring = (scan.ray // len(sensor.azimuths)).astype(np.uint16)
    cloud = np.zeros(len(scan.points), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("ring", "<u2")])
    cloud["x"], cloud["y"], cloud["z"] = scan.points[:, :3].T
    cloud["ring"] = ring
    boxes = Boxes(np.array([[10.0, 0.0, -0.9]]), np.array([[4.2, 1.8, 1.5]]), np.zeros(1), ["Car"], np.array([0.9]))
    pipeline = Pipeline(PipelineConfig(backend="input"))
    assert pipeline.beam_model.due()
    pipeline.process_messages(create_cloud(cloud, None, "lidar", 0), detection_array_from_boxes(boxes, "lidar", 0))
    assert pipeline.beam_model.model.rings == 32  # every ring, also those all within MIN_RANGE
    # an organized cloud (one row per beam, NaN where no return), no ring field
    rows = np.full((sensor.beams, len(sensor.azimuths), 3), np.nan, np.float32)
    rows.reshape(-1, 3)[scan.ray] = scan.points[:, :3]
    pipeline = Pipeline(PipelineConfig(backend="input"))
    pipeline.process_messages(create_cloud(rows, ["x", "y", "z"], "lidar", 0),
                              detection_array_from_boxes(boxes, "lidar", 0))
    assert pipeline.beam_model.model.rings == 32


def test_pcc_synth_sensor_is_stored_and_read_back(tmp_path, caplog):
    """``pcc synth --sensor`` simulates that layout and says so in meta.json; the filter reads
    the same table from the scans it wrote."""
    import json

    from pcc_ros.cli.main import main

    out = tmp_path / "synth"
    assert main(["synth", "--out", str(out), "--sequences", "1", "--frames", "1", "--seed", "3",
                 "--sensor", "vlp16"]) == 0
    meta = json.loads((out / "meta.json").read_text())
    assert meta["parameters"]["sensor"]["layout"] == "vlp16"
    scan = np.fromfile(out / "training" / "velodyne" / "0000" / "000000.bin", np.float32).reshape(-1, 4)
    found = estimate_sensor(scan)
    table = np.asarray(SENSOR_PRESETS["vlp16"].elevations_deg)
    assert found.rings >= 12  # the beams seen beyond MIN_RANGE (the steepest meet the ground nearer)
    assert np.abs(np.asarray(found.elevations_deg)[:, None] - table).min(axis=1).max() < 1e-3
    assert found.azimuth_resolution_deg == pytest.approx(0.2, rel=0.01)
    rc, text = run_cli(["synth", "--out", tmp_path / "x", "--frames", "1", "--sensor", "vlp16", "--low-res"], caplog)
    assert_named_failure(rc, text, "--low-res is a variant of the hdl64 layout", "drop it", output=tmp_path / "x")


def test_retries_back_off_on_a_scanner_without_beams():
    """A scan that never shows beam structure (a non-repetitive scanner) is retried after retry_every
    frames, then twice as long each time, up to recheck_every: not an estimate's cost every few frames."""
    noise = np.random.default_rng(1).uniform(-30, 30, (5000, 3))
    model = BeamModel("auto", recheck_every=16, retry_every=2)
    tried = []
    for frame in range(60):
        if model.due():
            tried.append(frame)
        model.for_frame(noise)
    assert tried == [0, 2, 6, 14, 30, 46] and model.estimates == 6 and model.model is None


def test_an_off_height_mount_is_warned_about_whenever_it_is_read(caplog):
    """The warning that the preset's threshold was set for a car-roof mount comes when the height is
    first read off, also at a later estimate that does not change the threshold, once per time."""
    from pcc_ros.pipeline.config import PipelineConfig
    from pcc_ros.pipeline.core import Pipeline

    pipeline = Pipeline(PipelineConfig(backend="input"))  # the shipped filter file's sensor_thresholds
    model = pipeline.beam_model
    model.model, model.preset, model.mount_height = sensor_preset("vlp16"), "vlp16", 1.75

    def warnings() -> int:
        return sum("above the ground" in r.getMessage() for r in caplog.records if r.levelno == logging.WARNING)

    with caplog.at_level(logging.WARNING, logger="pcc_ros"):
        pipeline.reject_threshold()
        assert warnings() == 0
        model.mount_height = 0.8  # a later estimate: the threshold in force stays the vlp16 entry
        pipeline.reject_threshold()
        pipeline.reject_threshold()
        assert warnings() == 1
        model.mount_height = 1.7
        pipeline.reject_threshold()
        model.mount_height = 2.5
        pipeline.reject_threshold()
        assert warnings() == 2
