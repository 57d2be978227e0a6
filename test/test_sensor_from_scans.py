"""A user's LiDAR read from its own scans (``pcc calibrate-filter --sensor-from``): the beam model
and mounting height of real KITTI and nuScenes scans, of a simulated sensor no preset describes,
the command end to end, and the errors it names."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from pcc_ros.cli.main import main
from pcc_ros.data.synthetic import generate
from pcc_ros.data.synthetic.lidar import Sensor
from pcc_ros.errors import ConfigError, DataError
from pcc_ros.pipeline.config import PipelineConfig
from pcc_ros.pipeline.filter import parse_sensor_thresholds
from pcc_ros.workflows.detection_eval import default_config
from pcc_ros.workflows.sensor_from_scans import ground_height, scanned_sensor

#: A 24-beam layout no preset has (uneven spacing, 0.25 deg step), mounted lower than KITTI's.
ODD_TABLE = (6.0, 3.0, 1.5, 0.5, -0.5, -1.5, -2.5, -3.5, -4.5, -5.5, -6.5, -7.5, -8.5, -9.5, -10.5, -11.5,
             -12.5, -13.5, -14.5, -16.0, -18.0, -20.0, -22.0, -25.0)


@pytest.fixture(scope="module")
def odd_scans(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("odd") / "scans"
    sensor = Sensor(layout="odd24", elevation_table=ODD_TABLE, azimuth_step=0.25, mount_height=1.3)
    generate(out, 1, 2, 5, sensor=sensor, test_fraction=0.0, progress=False)
    return out


def test_real_scans_read_as_their_sensors(shared_data):
    """KITTI's ring-less HDL-64E and nuScenes' HDL-32E with its ring field: the preset each is,
    and the height above the ground their datasets give (1.73 m; 1.84 m)."""
    kitti = scanned_sensor(shared_data / "kitti_tracking", scans=3)
    assert kitti.preset == "hdl64" and not kitti.ring_field and kitti.agreeing == 3
    assert kitti.mount_height == pytest.approx(1.73, abs=0.1)
    nus = scanned_sensor(shared_data / "nuscenes_mini", scans=3)
    assert nus.preset == "hdl32" and nus.ring_field and nus.model.rings == 32
    assert nus.mount_height == pytest.approx(1.84, abs=0.15)  # its road rises 0.35 m over 4-20 m


def test_a_bag_of_scans_reads_as_its_sensor(shared_data, tmp_path):
    """The user's path of the docs: scans in an MCAP bag (the nuScenes frame converted, its ring
    field carried in the PointCloud2) read as the HDL-32E they are."""
    bag = tmp_path / "drive"
    assert main(["convert", "nuscenes", str(shared_data / "nuscenes_mini"), "--out", str(bag)]) == 0
    scanned = scanned_sensor(bag)
    assert scanned.preset == "hdl32" and scanned.ring_field and scanned.mount_height == pytest.approx(1.84, abs=0.15)


def test_a_sensor_no_preset_describes_is_read_from_its_scans(odd_scans):
    scanned = scanned_sensor(odd_scans, scans=2)
    assert scanned.preset is None and scanned.agreeing == 2
    assert scanned.mount_height == pytest.approx(1.3, abs=0.08)
    assert scanned.model.azimuth_resolution_deg == pytest.approx(0.25, rel=0.05)
    est = np.asarray(scanned.model.elevations_deg)
    # the beams steeper than atan(1.3 / 5) = 14.6 deg reach the ground within the 5 m a ring-less
    # estimate starts at: not seen
    seen = np.asarray([e for e in ODD_TABLE if e > -14.6])
    assert np.abs(np.subtract.outer(seen, est)).min(axis=1).max() < 0.3  # every beam it shows is found
    sensor = scanned.sensor()
    assert sensor.model.elevations_deg == scanned.model.elevations_deg and sensor.mount_height == pytest.approx(1.3,
                                                                                                               abs=0.08)


def test_ground_height_needs_a_ground():
    rng = np.random.default_rng(0)
    sky = np.c_[rng.uniform(-30, 30, (5000, 2)), rng.uniform(0.5, 5.0, 5000)]  # nothing below the sensor
    assert ground_height(sky) is None
    r, a = rng.uniform(3, 25, 6000), rng.uniform(-np.pi, np.pi, 6000)
    flat = np.c_[r * np.cos(a), r * np.sin(a), np.full(6000, -0.6) + rng.normal(0, 0.01, 6000)]
    assert ground_height(flat) == pytest.approx(0.6, abs=0.03)


def test_cli_calibrates_a_threshold_for_the_scanned_sensor(odd_scans, tmp_path):
    """The threshold set on the scanned sensor's simulation, for the shipped weights, for every
    sensor (no per-preset table); the weights and their provenance kept; rerun identical."""
    args = ["calibrate-filter", "--sensor-from", str(odd_scans), "--sensor-scans", "2", "--sim-root",
            str(tmp_path / "sim"), "--sim-sequences", "2", "--sim-frames", "2", "--threshold-folds", "1",
            "--target-lost", "0.5", "--rows-cache", str(tmp_path / "rows")]
    assert main([*args, "--out", str(tmp_path / "a.yaml"), "--json", str(tmp_path / "a.json")]) == 0
    assert main([*args, "--out", str(tmp_path / "b.yaml")]) == 0
    text = (tmp_path / "a.yaml").read_text()
    assert text == (tmp_path / "b.yaml").read_text()
    report = json.loads((tmp_path / "a.json").read_text())
    assert report["sensor"]["matching_preset"] is None and report["sensor"]["beams"] >= 18
    config = PipelineConfig.from_yaml(tmp_path / "a.yaml").filter
    shipped = PipelineConfig.from_yaml(default_config()).filter
    assert parse_sensor_thresholds(config.sensor_thresholds) == {}
    assert config.reject_threshold == pytest.approx(report["threshold"]["threshold"], abs=1e-4)
    assert np.allclose(config.weights, shipped.weights) and config.w_bias == shipped.w_bias
    header = [line for line in text.splitlines() if line.startswith("# calibrated:")]
    assert any("--sim-sensors" in line for line in header) and any("--sensor-from" in line for line in header)
    simulated = json.loads((Path(report["sim_root"]) / "meta.json").read_text())["parameters"]["sensor"]
    assert simulated["mount_height"] == pytest.approx(1.3, abs=0.08) and len(simulated["elevation_table"]) >= 18


def test_the_simulation_avoids_the_seed_the_trees_were_boosted_on(odd_scans, tmp_path, caplog):
    """By default the scanned sensor's streets use seed 2027, not the shipped trees' 11 (scenes the trees
    saw make the threshold optimistic); asked for seed 11, it warns."""
    args = ["calibrate-filter", "--sensor-from", str(odd_scans), "--sensor-scans", "2", "--sim-root",
            str(tmp_path / "sim"), "--sim-sequences", "2", "--sim-frames", "2", "--threshold-folds", "1",
            "--target-lost", "0.5", "--rows-cache", str(tmp_path / "rows")]
    assert main([*args, "--json", str(tmp_path / "a.json")]) == 0
    assert Path(json.loads((tmp_path / "a.json").read_text())["sim_root"]).name.endswith("_s2027")
    assert "boosted on that seed" not in caplog.text
    assert main([*args, "--sim-seed", "11"]) == 0
    assert "--sim-seed 11: the trees of" in caplog.text


def test_cli_names_what_it_cannot_read(tmp_path, caplog):
    empty = tmp_path / "empty"
    (empty / "training" / "velodyne" / "0000").mkdir(parents=True)
    (empty / "training" / "label_02").mkdir(parents=True)
    assert main(["calibrate-filter", "--sensor-from", str(empty), "--sim-root", str(tmp_path / "sim")]) != 0
    assert str(empty) in caplog.text  # one line naming the file, no traceback
    with pytest.raises((DataError, ConfigError), match="empty"):
        scanned_sensor(empty)
    with pytest.raises(ConfigError, match="sensor-scans"):
        scanned_sensor(empty, scans=0)
    with pytest.raises(ConfigError, match="sensor-height"):
        scanned_sensor(empty, height=12.0)


def test_a_known_height_replaces_the_estimate(odd_scans):
    assert scanned_sensor(odd_scans, scans=2, height=0.9).mount_height == 0.9


def test_synth_simulates_the_scanned_sensor(odd_scans, tmp_path):
    """``pcc synth --sensor-from``: SynthCars with the sensor read from the scans (meta.json
    records its table and the height given), and a preview re-simulated from meta.json."""
    out = tmp_path / "mine"
    assert main(["synth", "--out", str(out), "--sequences", "1", "--frames", "2", "--seed", "3", "--sensor-from",
                 str(odd_scans), "--sensor-scans", "2", "--sensor-height", "1.25", "--preview"]) == 0
    sensor = json.loads((out / "meta.json").read_text())["parameters"]["sensor"]
    assert sensor["layout"] == "scanned" and sensor["mount_height"] == 1.25  # as given
    assert len(sensor["elevation_table"]) >= 18 and (out / "preview.png").is_file()
    assert scanned_sensor(out, scans=2).preset is None
    assert main(["synth", "--out", str(tmp_path / "x"), "--sensor-from", str(odd_scans), "--sensor", "vlp16"]) != 0
