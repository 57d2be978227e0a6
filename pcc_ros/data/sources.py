"""One entry point from a path to frames: a bag, KITTI tracking / object, nuScenes or Argoverse 2.

``pcc extract`` and the other offline tools accept any of these without caring which,
so the choice of input format never leaks past this module.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

from pcc_ros.data import av2
from pcc_ros.data.bag import open_bag, read_frames
from pcc_ros.data.bag_writer import POINTS_TOPIC
from pcc_ros.data.kitti import KittiObject, KittiTracking
from pcc_ros.data.nuscenes import NuScenes
from pcc_ros.errors import DataError
from pcc_ros.types import Sample

BAG_SUFFIXES = (".mcap", ".db3")


def is_bag(path: Path) -> bool:
    """A rosbag2 directory (``metadata.yaml``) or a bare ``.mcap`` / ``.db3`` file."""
    return (path.is_dir() and (path / "metadata.yaml").exists()) or (path.is_file() and path.suffix in BAG_SUFFIXES)


def kind_of(path: str | Path) -> str:
    """``"bag"``, ``"kitti-tracking"``, ``"kitti-object"``, ``"nuscenes"`` or ``"av2"`` (a log or a
    split directory of logs); DataError otherwise."""
    path = Path(path)
    if not path.exists():
        raise DataError(f"{path}: no such file or directory")
    if is_bag(path):
        return "bag"
    for split in (path / "training", path):
        velodyne = split / "velodyne"
        if velodyne.is_dir():
            if any(p.is_dir() for p in velodyne.iterdir()):
                return "kitti-tracking"
            return "kitti-object"
    if path.is_dir() and any((v / "scene.json").exists() for v in path.glob("v1.0-*")):
        return "nuscenes"
    if av2.is_log(path) or (path.is_dir() and any(av2.is_log(p) for p in path.iterdir())):
        return "av2"
    raise DataError(f"{path}: not a bag, KITTI tracking / object directory, nuScenes root or Argoverse 2 log / split",
                    hint="`pcc check-data PATH` says what each layout needs")


def count_frames(path: str | Path, sequence: str | None = None) -> int | None:
    """How many frames :func:`open_frames` will yield, for a progress bar's total, from the
    bag's index or the KITTI scan files (no scan is read); ``None`` where it is not known
    cheaply (nuScenes)."""
    path = Path(path)
    kind = kind_of(path)
    if kind == "bag":
        with open_bag(path) as reader:
            return sum(c.msgcount or 0 for c in reader.connections if c.topic == POINTS_TOPIC) or None
    if kind == "kitti-tracking":  # the readers' own split and sequence lookup
        reader = KittiTracking(path)
        return sum(len(reader.scan_paths(s)) for s in ([sequence] if sequence else reader.sequences()))
    if kind == "kitti-object":
        return len(list((KittiObject(path).root / "velodyne").glob("*.bin")))
    if kind == "av2":
        return sum(len(av2.Av2Log(p).sweep_paths()) for p in _av2_logs(path, sequence))
    return None


def _av2_logs(path: Path, sequence: str | None) -> list[Path]:
    """The logs of an AV2 log / split directory, or the one named ``sequence`` (its log id)."""
    logs = av2.log_dirs(path)
    if sequence is None:
        return logs
    chosen = [p for p in logs if p.name == sequence]
    if not chosen:
        raise DataError(f"{path}: no Argoverse 2 log {sequence!r} (have {', '.join(p.name for p in logs[:10])}"
                        f"{' ...' if len(logs) > 10 else ''})")
    return chosen


def open_frames(
    path: str | Path,
    sequence: str | None = None,
    detections_dir: str | Path | None = None,
    version: str | None = None,
) -> Iterator[Sample]:
    """Frames from a bag, KITTI tracking (``sequence`` or every sequence), KITTI object, nuScenes or
    Argoverse 2 (``sequence`` = a log id of a split directory, or every log; points in ``up_lidar``).

    ``detections_dir`` adds detector results to KITTI frames (bags carry their own);
    ``version`` picks the nuScenes table version (default: the only ``v1.0-*`` present).
    """
    path = Path(path)
    kind = kind_of(path)
    if kind == "bag":
        return read_frames(path)
    if kind == "kitti-tracking":
        reader = KittiTracking(path)
        sequences = [sequence] if sequence else reader.sequences()
        return (f for s in sequences for f in reader.frames(s, detections_dir))
    if kind == "kitti-object":
        return KittiObject(path).frames(detections_dir)
    if kind == "av2":
        return (f for log_dir in _av2_logs(path, sequence) for f in av2.Av2Log(log_dir).frames())

    if version is None:
        versions = sorted(v.name for v in path.glob("v1.0-*") if (v / "scene.json").exists())
        if len(versions) != 1:
            raise DataError(f"{path}: several nuScenes versions {versions}; choose one")
        version = versions[0]
    return NuScenes(path, version).frames(sequence)
