"""Generate a SynthCars LiDAR dataset (KITTI tracking layout with ground-truth car shapes)."""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

from pcc_ros.assignments import parse_assignments
from pcc_ros.data.synthetic.detector import DetectorParams
from pcc_ros.errors import ConfigError
from pcc_ros.geometry.beams import SENSOR_PRESETS

log = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, required=True, help="output directory (KITTI tracking layout)")
    parser.add_argument("--sequences", type=int, default=4, help="number of sequences (default 4)")
    parser.add_argument("--frames", type=int, default=50, help="frames per sequence, 10 Hz (default 50)")
    parser.add_argument("--seed", type=int, default=0, help="random seed: same seed, same bytes")
    parser.add_argument("--test-fraction", type=float, default=0.2, help="share of sequences in the test split")
    parser.add_argument("--shape-points", type=int, default=16384, help="points per ground-truth shape (>= 16384)")
    parser.add_argument("--sensor", default="hdl64", choices=tuple(SENSOR_PRESETS),
                        help="beam layout of the simulated LiDAR (default hdl64, KITTI's; stored in meta.json)")
    parser.add_argument("--sensor-from", type=Path, metavar="SCANS",
                        help="simulate YOUR LiDAR: its beam model and height read from a few of its scans (a bag / "
                        "MCAP, KITTI, nuScenes or Argoverse 2 path), as pcc calibrate-filter --sensor-from does")
    parser.add_argument("--sensor-scans", type=int, default=5, help="with --sensor-from: scans read (5)")
    parser.add_argument("--sensor-height", type=float,
                        help="with --sensor-from: the sensor's height above the ground in metres (default: read from "
                        "the scans)")
    parser.add_argument("--low-res", action="store_true", help="16-beam, 0.8 deg HDL-64E variant (quick looks, tests)")
    parser.add_argument(
        "--realistic-sensor", action="store_true",
        help="add the real-scan artefacts the domain-gap comparison found missing: per-laser range / elevation "
        "residuals and mixed pixels at depth edges (Sensor.realistic)",
    )
    parser.add_argument(
        "--vehicle-mix", default=None, metavar="FAMILY=WEIGHT,...",
        help="vehicle families and their weights instead of the street mix, e.g. van=1,suv=1,pickup=1,truck=1 "
        "(families: sedan, hatchback, wagon (estate), suv, van, pickup, truck; weights need not sum to 1)",
    )
    parser.add_argument("--overwrite", action="store_true", help="replace a dataset made with other parameters")
    parser.add_argument("--preview", action="store_true", help="also write preview.png (BEV of one frame)")
    parser.add_argument("--preview-sequence", type=int, default=0, help="sequence shown by --preview")
    parser.add_argument("--preview-frame", type=int, default=None, help="frame shown by --preview (default: middle)")


def parse_vehicle_mix(text: str) -> tuple[tuple[str, float], ...]:
    """``van=1,suv=2,estate=1`` -> ``(("van", 1.0), ("suv", 2.0), ("wagon", 1.0))`` for
    ``SceneParams.vehicle_mix``; an unknown family or a bad weight is a :class:`ConfigError`."""
    from pcc_ros.data.synthetic.vehicles import family_weights

    items = parse_assignments([t.strip() for t in text.split(",") if t.strip()], "--vehicle-mix", "FAMILY=WEIGHT")
    try:
        return tuple(family_weights([(name, float(weight)) for name, weight in items.items()]).items())
    except ValueError as exc:
        raise ConfigError(f"--vehicle-mix: {exc}") from None


def run(args: argparse.Namespace) -> int:
    from pcc_ros.data.synthetic.generator import generate
    from pcc_ros.data.synthetic.lidar import REALISTIC_ARTEFACTS, Sensor
    from pcc_ros.data.synthetic.scene import SceneParams

    extra = REALISTIC_ARTEFACTS if args.realistic_sensor else {}
    if args.low_res and args.sensor != "hdl64":
        raise ConfigError("--low-res is a variant of the hdl64 layout; drop it or --sensor")
    if args.sensor_from:
        if args.low_res or args.sensor != "hdl64":
            raise ConfigError("--sensor-from reads the sensor from the scans; drop --sensor / --low-res")
        from dataclasses import replace

        from pcc_ros.workflows.sensor_from_scans import scanned_sensor

        scanned = scanned_sensor(args.sensor_from, args.sensor_scans, height=args.sensor_height)
        sensor = replace(scanned.sensor(), **extra)
        log.info("%s", scanned.describe())
    else:
        sensor = Sensor.low_res(**extra) if args.low_res else Sensor(layout=args.sensor, **extra)
    scene = SceneParams(vehicle_mix=parse_vehicle_mix(args.vehicle_mix)) if args.vehicle_mix else None
    meta = generate(args.out, args.sequences, args.frames, args.seed, sensor=sensor, scene=scene,
                    shape_points=args.shape_points, test_fraction=args.test_fraction, overwrite=args.overwrite)
    n_tracks = sum(len(s["tracks"]) for s in meta["sequences"].values())
    log.info("wrote %d sequences x %d frames, %d tracks to %s (train %s, test %s)", args.sequences, args.frames,
             n_tracks, args.out, meta["splits"]["train"], meta["splits"]["test"])
    if args.preview:
        path = write_preview(args.out, args.preview_sequence, args.preview_frame)
        log.info("preview: %s", path)
    return 0


def write_preview(root: Path, sequence: int = 0, frame: int | None = None) -> Path:
    """Re-simulate one frame of a generated dataset (deterministic) and draw it to ``root/preview.png``."""
    from pcc_ros.data.synthetic.generator import (
        FRAME_STREAM,
        SPLIT_CODES,
        LabelParams,
        build_sequence,
        seeded_rng,
        simulate_frame,
    )
    from pcc_ros.data.synthetic.lidar import Sensor
    from pcc_ros.data.synthetic.preview import render_bev
    from pcc_ros.data.synthetic.scene import SceneParams

    meta = json.loads((Path(root) / "meta.json").read_text())
    p = meta["parameters"]
    seed = p["seed"]
    if not 0 <= sequence < p["sequences"]:
        raise ConfigError(f"--preview-sequence {sequence} is outside 0..{p['sequences'] - 1}")
    frame = p["frames"] // 2 if frame is None else frame
    if not 0 <= frame < p["frames"]:
        raise ConfigError(f"--preview-frame {frame} is outside 0..{p['frames'] - 1}")
    sensor = Sensor(**{k: tuple(v) if isinstance(v, list) else v for k, v in p["sensor"].items()})
    scene = SceneParams(**{k: tuple(v) if isinstance(v, list) else v for k, v in p["scene"].items()})
    detector = DetectorParams(**{k: tuple(v) if isinstance(v, list) else v for k, v in p["detector"].items()})
    name = f"{sequence:04d}"
    split = "test" if name in meta["splits"]["test"] else "train"
    street = build_sequence(seed, sequence, p["frames"], split, scene)
    rng = seeded_rng(seed, SPLIT_CODES[split], sequence, FRAME_STREAM, frame)
    res = simulate_frame(street, frame, sensor, rng, detector, LabelParams(**p["labels"]))
    title = (f"SynthCars seq {name} frame {frame}: {len(res.scan.points)} points, "
             f"{int(res.detection_true.sum())} true / {int((~res.detection_true).sum())} false detections")
    return render_bev(res.scan.points, res.gt, res.detections, res.detection_true, Path(root) / "preview.png", title)
