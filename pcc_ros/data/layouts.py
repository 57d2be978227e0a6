"""Which dataset layout a folder holds and what it lacks, before a long conversion (``pcc check-data``).

The checks read names, sizes and table schemas only (no scan is parsed), so a whole split is
checked in seconds. A layout is recognised leniently (a KITTI root with ``label_02/`` but no
``velodyne/`` is still KITTI tracking, missing its scans) so the report can say what is
missing rather than "unknown". ``missing`` entries stop ``pcc convert`` / ``extract`` /
``eval --real``; ``notes`` are what the data lacks that some output needs (labels, poses).

:data:`DOWNLOADS` says where each dataset comes from; :func:`download_hint` is the message a
command that defaults to ``../shared/data`` gives a user without it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pcc_ros.data import av2
from pcc_ros.data.feather import read_columns, schema_columns
from pcc_ros.data.nuscenes import TABLES as NUSCENES_TABLES
from pcc_ros.errors import DataError

#: Layout -> where to get it and which parts the tools read (docs/datasets.md "Getting real data").
DOWNLOADS: dict[str, str] = {
    "KITTI tracking": "https://www.cvlibs.net/datasets/kitti/eval_tracking.php — Velodyne point clouds, "
                      "training labels, camera calibration (GPS/IMU for poses); PointRCNN detections per sequence: "
                      "github.com/xinshuoweng/AB3DMOT data/KITTI/detection/",
    "KITTI object": "https://www.cvlibs.net/datasets/kitti/eval_object.php?obj_benchmark=3d — Velodyne point "
                    "clouds, training labels, camera calibration",
    "nuScenes": "https://www.nuscenes.org/nuscenes#download — v1.0-mini (or trainval metadata + LiDAR blobs)",
    "AV2": "https://www.argoverse.org/av2.html#download-link — Argoverse 2 sensor dataset (per log: "
           "sensors/lidar, annotations.feather, calibration/, city_SE3_egovehicle.feather)",
}


def download_hint(kinds: tuple[str, ...] = tuple(DOWNLOADS)) -> str:
    """What to download for ``kinds`` (keys of :data:`DOWNLOADS`), as one hint line."""
    return ("get the data: " + "; ".join(f"{k}: {DOWNLOADS[k]}" for k in kinds)
            + " (docs/datasets.md, 'Getting real data'); `pcc check-data ROOT` checks a download")


@dataclass
class LayoutReport:
    """What :func:`check_layout` found at ``root``."""

    root: Path
    layout: str  # "KITTI tracking", "KITTI object", "nuScenes", "AV2 log", "AV2 split" or "unknown"
    found: list[str] = field(default_factory=list)
    missing: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return self.layout != "unknown" and not self.missing

    def lines(self) -> list[str]:
        out = [f"{self.root}: {self.layout} layout" + ("" if self.layout == "unknown" else
                                                        " — complete" if self.ok else " — INCOMPLETE")]
        out += [f"  found: {x}" for x in self.found]
        out += [f"  MISSING: {x}" for x in self.missing]
        out += [f"  note: {x}" for x in self.notes]
        return out


def _kitti_split(root: Path) -> Path | None:
    for split in (root / "training", root):
        if any((split / d).is_dir() for d in ("velodyne", "label_02", "label_2", "calib")):
            return split
    return None


def _check_kitti_tracking(split: Path, report: LayoutReport) -> None:
    velodyne = split / "velodyne"
    sequences = sorted(p for p in velodyne.iterdir() if p.is_dir()) if velodyne.is_dir() else []
    if not sequences:
        report.missing.append(f"{velodyne}/SSSS/*.bin: no sequence of scans")
    for seq in sequences:
        scans = sorted(seq.glob("*.bin"))
        numbers = sorted(int(p.stem) for p in scans if p.stem.isdigit())
        gaps = (numbers[-1] - numbers[0] + 1 - len(numbers)) if numbers else 0
        report.found.append(f"sequence {seq.name}: {len(scans)} scans" + (f", {gaps} missing in the numbering"
                                                                          if gaps else ""))
        if not scans or gaps:
            report.missing.append(f"{seq}: {'no scans' if not scans else f'{gaps} scan(s) missing in the numbering'}")
        for folder, what, needed in (("calib", "calibration", True), ("label_02", "labels", False),
                                     ("oxts", "OXTS poses", False)):
            path = split / folder / f"{seq.name}.txt"
            if path.is_file():
                continue
            if needed:
                report.missing.append(f"{path}: {what} (every command needs it)")
            else:
                report.notes.append(f"{path}: no {what} (" + ("no /ground_truth: extract and eval --real need "
                                                              "labels" if folder == "label_02" else
                                                              "no /tf: the bag has no ego poses") + ")")
    detections = split.parent / "detections" if split.name == "training" else split / "detections"
    for d in sorted(detections.iterdir()) if detections.is_dir() else []:
        report.found.append(f"detector results {d}")


def _check_kitti_object(split: Path, report: LayoutReport) -> None:
    scans = sorted((split / "velodyne").glob("*.bin"))
    report.found.append(f"{len(scans)} scans in {split / 'velodyne'}")
    if not scans:
        report.missing.append(f"{split / 'velodyne'}/FFFFFF.bin: no scans")
    for folder, needed in (("calib", True), ("label_2", False)):
        absent = [p.stem for p in scans if not (split / folder / f"{p.stem}.txt").is_file()]
        if not absent:
            continue
        text = f"{split / folder}/{absent[0]}.txt and {len(absent) - 1} more" if len(absent) > 1 else \
            f"{split / folder}/{absent[0]}.txt"
        if needed:
            report.missing.append(f"{text}: calibration (every command needs it)")
        else:
            report.notes.append(f"{text}: no labels (no /ground_truth for those scans)")


def _check_nuscenes(root: Path, report: LayoutReport) -> None:
    versions = sorted(p for p in root.glob("v1.0-*") if p.is_dir())
    for version in versions:
        absent = [f"{t}.json" for t in NUSCENES_TABLES if not (version / f"{t}.json").is_file()]
        report.found.append(f"tables {version.name}: {len(NUSCENES_TABLES) - len(absent)} of {len(NUSCENES_TABLES)}")
        if absent:
            report.missing.append(f"{version}: {', '.join(absent)}")
    lidar = root / "samples" / "LIDAR_TOP"
    count = sum(1 for _ in lidar.glob("*.pcd.bin")) if lidar.is_dir() else 0
    report.found.append(f"{count} LIDAR_TOP key-frame scans in {lidar}")
    if not count:
        report.missing.append(f"{lidar}/*.pcd.bin: no LiDAR key frames (the LiDAR blobs of the download)")


def _av2_markers(path: Path) -> bool:
    return (path / av2.LIDAR_DIR).is_dir() or (path / av2.ANNOTATIONS).is_file() or (path / av2.POSES).is_file()


def _check_table(path: Path, columns: tuple[str, ...], what: str, report: LayoutReport) -> None:
    if not path.is_file():
        report.missing.append(f"{path}: {what} missing")
        return
    try:
        have = schema_columns(path)
    except DataError as exc:
        report.missing.append(str(exc))
        return
    lacking = [c for c in columns if c not in have]
    if lacking:
        report.missing.append(f"{path}: {what} lacks column(s) {lacking}")


def check_av2_log(log: Path, report: LayoutReport) -> None:
    """The four parts of one AV2 log: sweeps (names, the first one's schema) and the three tables."""
    lidar = log / av2.LIDAR_DIR
    sweeps = sorted(lidar.glob("*.feather")) if lidar.is_dir() else []
    report.found.append(f"{log.name}: {len(sweeps)} sweeps")
    bad = [p.name for p in sweeps if not p.stem.isdigit()]
    if not sweeps:
        report.missing.append(f"{lidar}/<timestamp_ns>.feather: no LiDAR sweeps")
    elif bad:
        report.missing.append(f"{lidar / bad[0]}: a sweep must be named <timestamp_ns>.feather")
    else:
        _check_table(sweeps[0], av2.LIDAR_COLUMNS, "LiDAR sweep", report)
    if (log / av2.ANNOTATIONS).is_file():
        _check_table(log / av2.ANNOTATIONS, av2.ANNOTATION_COLUMNS, "annotations", report)
    else:  # the test split's logs have none
        report.notes.append(f"{log / av2.ANNOTATIONS}: no annotations (a test-split log: convert it with "
                            "--no-labels; extract and eval --real need labels)")
    _check_table(log / av2.CALIBRATION, av2.CALIBRATION_COLUMNS, "sensor calibration", report)
    _check_table(log / av2.POSES, av2.POSE_COLUMNS, "ego poses", report)
    if report.missing or not sweeps:
        return
    # the stamps the conversion will look up (small tables: a few thousand rows)
    stamps = np.array([int(p.stem) for p in sweeps], dtype=np.int64)
    try:
        poses = read_columns(log / av2.POSES, ("timestamp_ns",), "ego poses")["timestamp_ns"]
        without = np.setdiff1d(stamps, poses)
        if len(without):
            report.missing.append(f"{log / av2.POSES}: no pose at {len(without)} sweep time(s), first {without[0]}")
        if (log / av2.ANNOTATIONS).is_file():
            labelled = read_columns(log / av2.ANNOTATIONS, ("timestamp_ns",), "annotations")["timestamp_ns"]
            off = int(np.count_nonzero(~np.isin(labelled, stamps)))
            if off:
                report.notes.append(f"{log / av2.ANNOTATIONS}: {off} annotation(s) at a time without a sweep "
                                    "(counted and left out by the conversion)")
    except DataError as exc:
        report.missing.append(str(exc))


def check_layout(root: str | Path) -> LayoutReport:
    """The layout at ``root`` and what it lacks (see the module docstring)."""
    root = Path(root)
    if not root.exists():
        return LayoutReport(root, "unknown", missing=[f"{root}: does not exist"], notes=_download_notes())
    split = _kitti_split(root)
    if split is not None:
        velodyne = split / "velodyne"
        tracking = (split / "label_02").is_dir() or (velodyne.is_dir() and any(p.is_dir() for p in velodyne.iterdir()))
        report = LayoutReport(root, "KITTI tracking" if tracking else "KITTI object")
        (_check_kitti_tracking if tracking else _check_kitti_object)(split, report)
        return report
    if any(p.is_dir() for p in root.glob("v1.0-*")):
        report = LayoutReport(root, "nuScenes")
        _check_nuscenes(root, report)
        return report
    if _av2_markers(root):
        report = LayoutReport(root, "AV2 log")
        check_av2_log(root, report)
        return report
    logs = sorted(p for p in root.iterdir() if p.is_dir() and _av2_markers(p)) if root.is_dir() else []
    if logs:
        report = LayoutReport(root, "AV2 split")
        per_log = [LayoutReport(log, "AV2 log") for log in logs]
        for log, log_report in zip(logs, per_log):
            check_av2_log(log, log_report)
            report.missing += log_report.missing
            report.notes += log_report.notes
        report.found.append(f"{len(logs)} logs, {sum(r.ok for r in per_log)} complete")
        return report
    return LayoutReport(root, "unknown", missing=[
        f"{root}: no KITTI (velodyne/, label_02/ or label_2/, calib/; or training/ holding them), nuScenes "
        "(v1.0-*/ tables + samples/LIDAR_TOP/) or Argoverse 2 (LOG/sensors/lidar/, LOG/*.feather) layout"],
        notes=_download_notes())


def _download_notes() -> list[str]:
    return [f"get {name}: {where}" for name, where in DOWNLOADS.items()] + [
        "docs/datasets.md, 'Getting real data', says which files each command reads"]


def check_tree(root: str | Path) -> list[LayoutReport]:
    """:func:`check_layout` of ``root``, or, when ``root`` is no layout itself but a folder of datasets
    (``../shared/data``), of each of its sub-folders that is one."""
    report = check_layout(root)
    if report.layout != "unknown" or not Path(root).is_dir():
        return [report]
    inside = [check_layout(p) for p in sorted(Path(root).iterdir()) if p.is_dir()]
    inside = [r for r in inside if r.layout != "unknown"]
    return inside or [report]
