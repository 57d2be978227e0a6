"""Car instances: extraction from frames into the on-disk instance cache (``pcc extract``).

``pcc extract`` crops every car box of every frame, moves its points into the box's
canonical car frame and stores one *instance* (observation) per box in the cache that
:mod:`pcc_ros.data.instance_cache` describes and reads. Extraction is idempotent and
resumable: the index records the fingerprint of the inputs and options and the frames done.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import zlib
from collections import Counter
from collections.abc import Iterable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from pcc_ros import files
from pcc_ros.data.instance_cache import COLUMNS, FORMAT, VERSION, EvalShapes, InstanceCache, columns_to_arrays
from pcc_ros.errors import DataError
from pcc_ros.geometry.boxes import crop_canonical, iou_3d
from pcc_ros.geometry.canonical import to_canonical
from pcc_ros.types import Sample, class_mask

__all__ = [
    "EvalShapes",
    "ExtractConfig",
    "InstanceCache",
    "SynthCarsInfo",
    "extract_instances",
    "fingerprint",
    "frame_instances",
    "split_of",
]

log = logging.getLogger("pcc.extract")


@dataclass
class ExtractConfig:
    """Options of ``pcc extract``; all of them enter the cache fingerprint."""

    classes: tuple[str, ...] = ("Car", "Van")
    min_points: int = 10
    boxes: str = "ground_truth"  # or "detections"
    margin: float = 0.0
    ground_margin: float = 0.1
    val_fraction: float = 0.1
    test_fraction: float = 0.2
    shard_points: int = 2_000_000
    match_iou: float = 0.5

    def __post_init__(self) -> None:
        if self.boxes not in ("ground_truth", "detections"):
            raise DataError(f"--boxes must be ground_truth or detections, got {self.boxes!r}")
        self.classes = tuple(self.classes)


# --------------------------------------------------------------------------- helpers


def _bucket(key: str) -> float:
    """Deterministic value in [0, 1) per key (crc32: stable across runs and machines)."""
    return zlib.crc32(key.encode()) / 2**32


def split_of(sequence: str, track_key: str, synth_splits: dict[str, str] | None, config: ExtractConfig) -> str:
    """Split of a track: SynthCars test sequences are test; everything else by a hash of the track."""
    u = _bucket(f"{sequence}/{track_key}")
    if synth_splits is not None and sequence in synth_splits:
        if synth_splits[sequence] == "test":
            return "test"
        return "val" if u < config.val_fraction else "train"
    if u < config.test_fraction:
        return "test"
    if u < config.test_fraction + config.val_fraction:
        return "val"
    return "train"


def _tree_signature(path: Path) -> dict:
    """Cheap content signature of the input (file count, bytes, newest mtime)."""
    path = path.resolve()
    if path.is_file():
        st = path.stat()
        return {"files": 1, "bytes": st.st_size, "mtime_ns": st.st_mtime_ns}
    files = total = newest = 0
    for root, _dirs, names in os.walk(path):
        for name in names:
            try:
                st = os.stat(os.path.join(root, name))
            except OSError:
                continue
            files += 1
            total += st.st_size
            newest = max(newest, st.st_mtime_ns)
    return {"files": files, "bytes": total, "mtime_ns": newest}


def fingerprint(source: str | Path | None, config: ExtractConfig, extra: dict | None = None) -> str:
    """Hash of the input's signature and every option: a cache is reused only when it matches."""
    payload = {
        "format": FORMAT,
        "version": VERSION,
        "config": asdict(config),
        "source": None if source is None else {"path": str(Path(source).resolve()), **_tree_signature(Path(source))},
        "extra": extra or {},
    }
    return hashlib.sha256(json.dumps(payload, sort_keys=True, default=str).encode()).hexdigest()[:32]


#: What an (even interrupted) extraction leaves in its directory; anything else is not ours.
_CACHE_ENTRIES = ("index.json", "shards", "eval_shapes", "info.png")


def _only_cache_entries(out: Path) -> bool:
    """``out`` holds nothing but what :func:`extract_instances` writes (and its temporaries)."""
    return all(p.name in _CACHE_ENTRIES or files.TMP_MARK in p.name for p in out.iterdir())


# --------------------------------------------------------------------------- extraction


@dataclass
class SynthCarsInfo:
    """What extraction needs from a SynthCars root: sequence splits and the shapes."""

    root: Path
    splits: dict[str, str]

    @classmethod
    def detect(cls, root: str | Path | None) -> SynthCarsInfo | None:
        """SynthCars info when ``root`` has ``meta.json`` with splits and a ``shapes/`` folder."""
        if root is None:
            return None
        root = Path(root)
        meta_path = root / "meta.json"
        if not (meta_path.is_file() and (root / "shapes").is_dir()):
            return None
        try:
            meta = json.loads(meta_path.read_text())
            splits = {seq: split for split, names in meta["splits"].items() for seq in names}
        except (OSError, ValueError, KeyError, AttributeError, TypeError) as exc:
            raise DataError(f"{meta_path}: unreadable SynthCars meta.json ({exc})") from exc
        return cls(root, splits)


@dataclass
class _Shard:
    points: list[np.ndarray] = field(default_factory=list)
    columns: dict[str, list] = field(default_factory=lambda: {k: [] for k in COLUMNS})
    n_points: int = 0

    def __len__(self) -> int:
        return len(self.points)


def frame_instances(
    frame: Sample, config: ExtractConfig, synth: SynthCarsInfo | None = None, skipped: Counter | None = None
) -> tuple[list[np.ndarray], dict[str, list]]:
    """Canonical crops and metadata columns of the wanted boxes of one frame.

    Invalid boxes (NaN, non-positive size) and crops under ``min_points`` are skipped and
    counted in ``skipped`` (a Counter), never raised: one bad box must not stop a run.
    """
    skipped = Counter() if skipped is None else skipped
    columns: dict[str, list] = {k: [] for k in COLUMNS}
    boxes = frame.ground_truth if config.boxes == "ground_truth" else frame.detections
    if boxes is None or len(boxes) == 0:
        return [], columns
    boxes = boxes[class_mask(boxes.label, config.classes)]
    valid = boxes.valid_mask()
    if not valid.all():
        skipped["invalid_box"] += int((~valid).sum())
    boxes = boxes[valid]
    if len(boxes) == 0:
        return [], columns
    points = np.asarray(frame.points)
    _, crops = crop_canonical(points, boxes, margin=config.margin, ground_margin=config.ground_margin)
    gt_track = np.full(len(boxes), "", dtype=object)
    gt_iou = np.full(len(boxes), np.nan, dtype=np.float32)
    if config.boxes == "detections" and frame.ground_truth is not None and len(frame.ground_truth):
        gt = frame.ground_truth[frame.ground_truth.valid_mask()]
        if len(gt):
            iou = iou_3d(boxes, gt)
            best = iou.argmax(axis=1)
            gt_iou = iou.max(axis=1).astype(np.float32)
            matched = gt_iou >= config.match_iou
            gt_track[matched] = gt.track_id[best[matched]]
    origins = np.stack([to_canonical(np.zeros((1, 3)), c, y, s[0])[0] for c, y, s in
                        zip(boxes.center, boxes.yaw, boxes.size)]).astype(np.float32) if len(boxes) else None
    pose = np.full((4, 4), np.nan) if frame.pose is None else np.asarray(frame.pose, dtype=np.float64)
    kept = []
    for i, crop in enumerate(crops):  # loop over boxes of one frame (tens), metadata only
        if len(crop) < max(config.min_points, 1):
            skipped["too_few_points"] += 1
            continue
        track = str(boxes.track_id[i])
        track_key = track or f"f{frame.index}b{i}"
        seq = str(frame.sequence)
        values = {
            "sequence": seq, "frame": int(frame.index), "stamp_ns": int(frame.stamp_ns), "track": track,
            "label": str(boxes.label[i]), "score": float(boxes.score[i]), "box_center": boxes.center[i],
            "box_size": boxes.size[i], "box_yaw": float(boxes.yaw[i]), "origin": origins[i],
            "distance": float(np.linalg.norm(boxes.center[i])), "num_points": len(crop),
            "split": split_of(seq, track_key, None if synth is None else synth.splits, config),
            "pose": pose, "gt_track": str(gt_track[i]), "gt_iou": float(gt_iou[i]),
            "has_shape": False,
        }
        for k, v in values.items():
            columns[k].append(v)
        kept.append(crop)
    return kept, columns



class _Writer:
    """Accumulates instances and writes shards; the index records progress after each."""

    def __init__(self, root: Path, index: dict, config: ExtractConfig, synth: SynthCarsInfo | None) -> None:
        self.root, self.index, self.config, self.synth = root, index, config, synth
        self.shard = _Shard()
        self.shapes_done: set[tuple[str, str]] = set()

    def add(self, crops: list[np.ndarray], columns: dict[str, list]) -> None:
        if self.synth is not None:
            for j, (seq, track) in enumerate(zip(columns["sequence"], columns["track"])):
                columns["has_shape"][j] = self._copy_shape(seq, track)
        self.shard.points.extend(crops)
        for k, v in columns.items():
            self.shard.columns[k].extend(v)
        self.shard.n_points += sum(len(c) for c in crops)

    def _copy_shape(self, sequence: str, track: str) -> bool:
        """Copy the SynthCars shape of a track into ``eval_shapes/`` (once per track)."""
        if not track:
            return False
        dest = self.root / "eval_shapes" / sequence / f"{track}.npy"
        if (sequence, track) in self.shapes_done or dest.exists():
            self.shapes_done.add((sequence, track))
            return True
        from pcc_ros.data.synthetic import load_shape

        try:
            shape = load_shape(self.synth.root, sequence, track)
        except ValueError:  # non-numeric track id: no SynthCars shape
            return False
        if shape is None:
            return False
        dest.parent.mkdir(parents=True, exist_ok=True)
        files.save_npy(dest, shape.astype(np.float32))
        self.shapes_done.add((sequence, track))
        return True

    def full(self) -> bool:
        return self.shard.n_points >= self.config.shard_points

    def flush(self, frames_done: int) -> None:
        """Write the pending shard (if any) and record ``frames_done`` in the index."""
        if len(self.shard):
            number = len(self.index["shards"])
            name = f"{number:05d}"
            shards = self.root / "shards"
            shards.mkdir(exist_ok=True)
            counts = np.array([len(p) for p in self.shard.points], dtype=np.int64)
            offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
            points = np.concatenate(self.shard.points).astype(np.float32).reshape(-1, 3)
            files.save_npy(shards / f"{name}.points.npy", points)
            files.save_npy(shards / f"{name}.offsets.npy", offsets)
            files.save_npz(shards / f"{name}.meta.npz", **columns_to_arrays(self.shard.columns))
            self.index["shards"].append({"name": name, "instances": len(counts), "points": int(offsets[-1])})
            self.shard = _Shard()
        self.index["frames_done"] = frames_done
        files.write_json(self.root / "index.json", self.index, indent=1, sort_keys=True)


def _clear_cache(out: Path) -> None:
    for sub in ("shards", "eval_shapes"):
        shutil.rmtree(out / sub, ignore_errors=True)
    (out / "index.json").unlink(missing_ok=True)


def extract_instances(
    frames: Iterable[Sample],
    out: str | Path,
    config: ExtractConfig | None = None,
    *,
    source: str | Path | None = None,
    synthcars: str | Path | None = None,
    force: bool = False,
    progress: bool = True,
    total: int | None = None,
) -> InstanceCache:
    """Extract instances from ``frames`` into the cache directory ``out``.

    Idempotent and resumable: the cache's fingerprint covers ``source`` (path + file
    signature) and ``config``. A complete cache with the same fingerprint is returned as
    is; an interrupted one resumes after the frames already stored; a cache made from
    other inputs or options is an error unless ``force`` (then it is rebuilt).

    Args:
        frames: the frames, in a deterministic order (resuming skips a prefix).
        source: the input path, for the fingerprint (``None``: frames are hashed by nothing,
            so only ``force`` or an absent cache lead to extraction).
        synthcars: a SynthCars root: its splits and ground-truth shapes are used
            (default: ``source`` when it is one).
    """
    config = config or ExtractConfig()
    out = Path(out)
    synth = SynthCarsInfo.detect(synthcars if synthcars is not None else source)
    fp = fingerprint(source, config, {"synthcars": None if synth is None else str(synth.root.resolve())})
    index_path = out / "index.json"
    index = None
    if index_path.exists():
        try:
            index = json.loads(index_path.read_text())
        except (OSError, ValueError) as exc:
            if not force:
                raise DataError(f"{index_path}: unreadable cache index ({exc}); use --force to rebuild") from exc
        if index is not None and index.get("format") != FORMAT and not force:
            raise DataError(f"{out}: not a pcc instance cache; refusing to overwrite")
        if index is not None and index.get("fingerprint") != fp:
            if not force:
                raise DataError(f"{out}: cache was built from other inputs or options; use --force to rebuild")
            index = None
        if force and index is not None:
            index = None
        if index is None:
            _clear_cache(out)
    elif out.exists() and any(out.iterdir()):
        if not _only_cache_entries(out):
            raise DataError(f"{out}: exists and is not an instance cache",
                            hint="choose an empty or new directory")
        # an extraction interrupted before it recorded any progress: nothing to resume
        log.info("%s: no index.json (interrupted before any progress was recorded); starting over", out)
        _clear_cache(out)
    if index is not None and index.get("complete"):
        log.info("%s: up to date (%d instances), nothing to do", out, sum(s["instances"] for s in index["shards"]))
        return InstanceCache.load(out)
    created = not out.exists()
    out.mkdir(parents=True, exist_ok=True)
    files.remove_stale_temporaries(out)
    if index is None:
        index = {"format": FORMAT, "version": VERSION, "fingerprint": fp, "config": asdict(config),
                 "source": None if source is None else str(source),
                 "synthcars": None if synth is None else str(synth.root.resolve()),  # read back from any directory
                 "shards": [], "frames_done": 0, "complete": False, "skipped": {}}
        files.write_json(index_path, index, indent=1, sort_keys=True)  # from now on the directory is recognisably ours
    # Shards written after the last recorded progress are orphans of an interrupted run.
    known = {s["name"] for s in index["shards"]}
    for leftover in (out / "shards").glob("*") if (out / "shards").exists() else []:
        if leftover.name.split(".")[0] not in known:
            leftover.unlink()
    resume_from = int(index.get("frames_done", 0))
    if resume_from:
        log.info("%s: resuming after %d frames", out, resume_from)
    skipped = Counter(index.get("skipped", {}))
    writer = _Writer(out, index, config, synth)
    done = 0
    try:
        with tqdm(total=total, desc="extract", unit="frame", disable=not progress) as bar:
            for frame in frames:
                done += 1
                bar.update(1)
                if done <= resume_from:
                    continue
                crops, columns = frame_instances(frame, config, synth, skipped)
                writer.add(crops, columns)
                if writer.full():
                    index["skipped"] = dict(skipped)
                    writer.flush(done)
                bar.set_postfix(instances=sum(s["instances"] for s in index["shards"]) + len(writer.shard))
        if done < resume_from:
            raise DataError(f"{out}: the cache records {resume_from} frames done but the source has {done}",
                            hint="the source changed; re-run with --force to rebuild")
        index["skipped"] = dict(skipped)
        index["complete"] = True
        writer.flush(done)
    except BaseException:
        if created and not index["shards"]:  # nothing worth resuming: leave no partial output
            shutil.rmtree(out, ignore_errors=True)
        raise
    if skipped:
        log.info("skipped: %s", ", ".join(f"{k}={v}" for k, v in sorted(skipped.items())))
    return InstanceCache.load(out)
