"""Convert KITTI tracking / object, nuScenes, Argoverse 2 or SynthCars to a ROS 2 bag (MCAP + zstd or sqlite3).

Examples::

    pcc convert kitti-tracking data/kitti_tracking --sequence 0000 \\
        --detections data/kitti_tracking/detections/pointrcnn --out bags/kitti_0000
    pcc convert kitti-object data/kitti_object --out bags/kitti_object --storage sqlite3
    pcc convert nuscenes data/nuscenes --version v1.0-mini --scene scene-0061 --out bags/scene-0061
    pcc convert synth data/synthcars --sequence 0003 --out bags/synth_0003
    pcc convert av2 data/av2/val/LOG_ID --out bags/av2_log     # /points in up_lidar (--frame ego_vehicle: as recorded)
    pcc convert av2 data/av2/val/LOG_A data/av2/val/LOG_B --out bags/av2   # bags/av2/LOG_A, bags/av2/LOG_B
"""

from __future__ import annotations

import argparse
import logging
from itertools import islice
from pathlib import Path

from pcc_ros.data.av2 import DEFAULT_FRAME, EGO_FRAME, Av2Log, log_dirs
from pcc_ros.data.bag_writer import check_output_bag, write_bag
from pcc_ros.data.kitti import KittiObject, KittiTracking
from pcc_ros.data.nuscenes import NuScenes
from pcc_ros.errors import DataError

log = logging.getLogger("pcc.convert")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="source", metavar="SOURCE", required=True)
    helps = {
        "kitti-tracking": "KITTI tracking layout (velodyne/SSSS, label_02, calib, oxts)",
        "kitti-object": "KITTI object layout (velodyne, label_2, calib)",
        "nuscenes": "nuScenes v1.0 tables (LIDAR_TOP key frames)",
        "synth": "SynthCars output (KITTI tracking layout; its detections by default)",
        "av2": "Argoverse 2 sensor-dataset logs (feather tables); several logs or a split dir: one bag per log",
    }
    for name, text in helps.items():
        p = sub.add_parser(name, help=text, description=text)
        if name == "av2":
            p.add_argument("src", type=Path, nargs="+", help="log directories (or a split directory of logs)")
            p.add_argument("--frame", default=DEFAULT_FRAME,
                           help=f"frame of /points: a sensor of the calibration ({DEFAULT_FRAME}, the default: the "
                           f"scan frame's origin is then the viewpoint, as the nodes assume) or {EGO_FRAME} "
                           "(the points as recorded)")
            p.add_argument("--no-labels", action="store_true",
                           help="read no annotations.feather (test-split logs have none): no /ground_truth")
        else:
            p.add_argument("src", type=Path, help="dataset root")
        p.add_argument("--out", type=Path, required=True, help="output bag: a folder (rosbag2 writes metadata.yaml "
                       "and NAME.mcap / NAME.db3 inside it); av2 with several logs: the folder of one bag per log")
        p.add_argument("--storage", choices=("mcap", "sqlite3"), default="mcap", help="rosbag2 storage (mcap)")
        p.add_argument("--no-compress", action="store_true", help="write without zstd")
        p.add_argument("--zstd-level", type=int, default=None, help="MCAP chunk zstd level (default 3)")
        p.add_argument("--force", action="store_true", help="replace an existing bag")
        p.add_argument("--first", type=int, default=0, help="index of the first frame to convert")
        p.add_argument("--frames", type=int, default=None, help="number of frames (default: all)")
        if name not in ("nuscenes", "av2"):
            p.add_argument("--detections", type=Path, help="detector results (KITTI object format + score)")
        if name in ("kitti-tracking", "synth"):
            p.add_argument("--sequence", help="sequence (required when the dataset has several)")
        if name == "nuscenes":
            p.add_argument("--version", default="v1.0-mini", help="table version (v1.0-mini)")
            p.add_argument("--scene", help="scene name or token (default: every scene, by time)")


def _stop(args: argparse.Namespace) -> int | None:
    return None if args.frames is None else args.first + args.frames


def _tracking(args: argparse.Namespace, synth: bool):
    reader = KittiTracking(args.src)
    sequences = reader.sequences()
    sequence = args.sequence
    if sequence is None:
        if len(sequences) != 1:
            raise DataError(f"{args.src}: choose --sequence among {', '.join(sequences)} (one sequence per bag)")
        sequence = sequences[0]
    detections = args.detections
    if synth and detections is None and (args.src / "detections" / "synthetic").is_dir():
        detections = args.src / "detections" / "synthetic"
    total = len(reader.scan_paths(sequence)[args.first : _stop(args)])
    frames = reader.frames(sequence, detections, start=args.first, stop=_stop(args))
    return frames, total, f"{args.source} {args.src} sequence {sequence}"


def _object(args: argparse.Namespace):
    reader = KittiObject(args.src)
    total = len(sorted((reader.root / "velodyne").glob("*.bin"))[args.first : _stop(args)])
    return reader.frames(args.detections, start=args.first, stop=_stop(args)), total, f"kitti-object {args.src}"


def _nuscenes(args: argparse.Namespace):
    reader = NuScenes(args.src, args.version)
    if args.scene is None:  # every scene, in time order, so the bag's stamps increase
        first_stamp = {s["token"]: reader.samples[s["first_sample_token"]]["timestamp"] for s in reader.tables["scene"]}
        scenes = sorted(reader.tables["scene"], key=lambda s: first_stamp[s["token"]])
        names = [s["name"] for s in scenes]
    else:
        names = [args.scene]
    by_name = {s["name"]: s for s in reader.tables["scene"]}
    total = sum(int(by_name[n].get("nbr_samples", 0)) for n in names) if all(n in by_name for n in names) else None
    frames = islice((f for name in names for f in reader.frames(name)), args.first, _stop(args))
    if total is not None:
        total = max(0, min(total, _stop(args) or total) - args.first)
    return frames, total, f"nuscenes {args.src} {args.version} {args.scene or 'all scenes'}"


def _av2_jobs(args: argparse.Namespace) -> list[tuple[Path, Path]]:
    """``(log, bag)`` per log: one log to ``--out``, several to ``--out/<log id>`` (a bag is one recording:
    one city frame, increasing stamps)."""
    logs = [log_dir for src in args.src for log_dir in log_dirs(src)]
    names = [p.name for p in logs]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise DataError(f"log id(s) {twice} given twice; each log becomes one bag named by its id")
    if len(logs) == 1:
        return [(logs[0], args.out)]
    return [(log_dir, args.out / log_dir.name) for log_dir in logs]


def _write(args: argparse.Namespace, frames, total, source: str, out: Path) -> None:
    summary = write_bag(
        frames,
        out,
        storage=args.storage,
        compress=not args.no_compress,
        zstd_level=args.zstd_level,
        force=args.force,
        total=total,
        source=source,
    )
    topics = ", ".join(f"{t} {n}" for t, n in summary.messages.items())
    log.info("wrote %s: %d frames, %.1f MB (%s)", summary.path, summary.frames, summary.bytes / 1e6, topics)


def _av2(args: argparse.Namespace) -> int:
    jobs = _av2_jobs(args)
    for _, out in jobs:  # every output is checked before the first log is read
        check_output_bag(out, args.force)
    for log_dir, out in jobs:
        reader = Av2Log(log_dir, frame=args.frame, labels=not args.no_labels)
        reader.sensor_to_ego()  # an unknown --frame fails before any sweep is read
        total = len(reader.sweep_paths()[args.first : _stop(args)])
        frames = reader.frames(start=args.first, stop=_stop(args))
        _write(args, frames, total, f"av2 {log_dir} frame {args.frame}", out)
    return 0


def run(args: argparse.Namespace) -> int:
    if args.source == "av2":
        return _av2(args)
    check_output_bag(args.out, args.force)  # before the dataset is read
    if args.source in ("kitti-tracking", "synth"):
        frames, total, source = _tracking(args, synth=args.source == "synth")
    elif args.source == "kitti-object":
        frames, total, source = _object(args)
    else:
        frames, total, source = _nuscenes(args)
    _write(args, frames, total, source, args.out)
    return 0
