"""The filter on a LiDAR no preset describes: the shipped file against one calibrated from the
sensor's own scans (``pcc calibrate-filter --sensor-from``), on held-out simulated streets.

A 40-beam layout shaped after the Hesai Pandar40P datasheet (+15 to -25 deg, 1/3 deg spacing
around the horizon, 0.2 deg azimuth step) mounted 1.9 m high: the shipped file matches no preset
for it and judges it with its most lenient threshold. The scans the calibration reads are those of
the first street (no label used); both files are then judged on every street by the kind labels:

    python scripts/sensor_from_scans_check.py --root data/sensor_from_scans --json out/sensor_from_scans.json

Writes one JSON (the sensor, the estimate, the calibrated threshold, per street and file: cars
lost, false boxes removed per kind) for ``scripts/render_figures.py``, and each judgement's
operating curve beside its JSON under ``--root`` (``eval_<file>_s<seed>.png``).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from pcc_ros.cli.main import main as pcc
from pcc_ros.data.synthetic import generate
from pcc_ros.data.synthetic.lidar import Sensor
from pcc_ros.files import write_json
from pcc_ros.geometry.beams import SENSOR_PRESETS
from pcc_ros.workflows.detection_eval import default_config

UPPER = (15.0, 11.0, 8.0, 5.0, 3.0, 2.0)
LOWER = (-7.0, -8.0, -9.0, -10.0, -11.0, -12.0, -13.0, -14.0, -19.0, -25.0)
#: 40 beams: 6 above +2 deg, 24 at 1/3 deg from +1.67 to -6 deg, 10 below.
TABLE = UPPER + tuple(float(v) for v in np.round(np.arange(1.67, -6.0, -1 / 3), 2)) + LOWER
#: The sensors of the check: one no preset describes, and a preset's beams on a small robot
#: (it matches the vlp16 preset, whose threshold was set 1.73 m high).
SENSORS = {
    "pandar40p": Sensor(layout="pandar40p", elevation_table=TABLE, azimuth_step=0.2, mount_height=1.9),
    "vlp16_low": Sensor(layout="vlp16_low", elevation_table=SENSOR_PRESETS["vlp16"].elevations_deg,
                        azimuth_step=SENSOR_PRESETS["vlp16"].azimuth_resolution_deg, mount_height=0.8),
}


def _judge(street: Path, config: Path, out: Path) -> dict:
    code = pcc(["eval", "detections", "--kitti", str(street), "--gt-classes", "Car,Van", "--backend", "input",
                "--config", str(config), "--json", str(out), "--plot", str(out.with_suffix(".png"))])
    if code:
        raise SystemExit(f"pcc eval detections failed on {street} with {config}")
    d = json.loads(out.read_text())
    k = d["per_kind"]["configured"]
    return {"threshold": d["threshold_in_force"], "true": d["true"], "true_lost": k["true_lost"],
            "true_lost_count": k["true_lost_count"], "per_kind_count": k["per_group_count"],
            "per_kind_removed": k["per_group_removed"], "false_removed": k["false_removed"]}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--root", type=Path, default=Path("data/sensor_from_scans"))
    parser.add_argument("--sensor", choices=tuple(SENSORS), default="pandar40p", help="the sensor (pandar40p)")
    parser.add_argument("--seeds", default="8101,8102", help="the held-out streets (the first one's scans are read)")
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--json", type=Path, required=True)
    args = parser.parse_args()
    seeds = [int(s) for s in args.seeds.split(",")]
    sensor = SENSORS[args.sensor]
    streets = {s: args.root / f"{args.sensor}_s{s}" for s in seeds}
    for seed, street in streets.items():
        generate(street, 1, args.frames, seed, sensor=sensor, test_fraction=0.0)
    calibrated, report = args.root / f"calibrated_{args.sensor}.yaml", args.root / f"calibrated_{args.sensor}.json"
    if pcc(["calibrate-filter", "--sensor-from", str(streets[seeds[0]]), "--sim-root", str(args.root / "sim"),
            "--rows-cache", str(args.root / "rows"), "--out", str(calibrated), "--json", str(report)]):
        raise SystemExit("pcc calibrate-filter --sensor-from failed")
    files = {"shipped": default_config(), "calibrated": calibrated}
    result = {
        "sensor": {"name": args.sensor, "beams": len(sensor.elevation_table),
                   "elevations_deg": list(sensor.elevation_table), "azimuth_step_deg": sensor.azimuth_step,
                   "mount_height_m": sensor.mount_height},
        "calibration": json.loads(report.read_text()),
        "streets": {str(seed): {name: _judge(street, path, args.root / f"eval_{args.sensor}_{name}_s{seed}.json")
                                for name, path in files.items()} for seed, street in streets.items()},
    }
    args.json.parent.mkdir(parents=True, exist_ok=True)
    write_json(args.json, result, indent=1, nonfinite_null=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
