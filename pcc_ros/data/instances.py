"""Car instances: extraction from frames, the on-disk instance cache, training views.

``pcc extract`` crops every car box of every frame, moves its points into the box's
canonical car frame and stores one *instance* (observation) per box. Training and
evaluation read the cache only through :class:`InstanceCache`.

Cache layout (a directory; numpy only, no pickle; point shards memory-mappable)::

    CACHE/index.json                      format, version, fingerprint of the inputs and
                                          options, shard list, progress, complete flag
    CACHE/shards/NNNNN.points.npy         float32 (P, 3) canonical points of the shard,
                                          instances back to back (CSR values)
    CACHE/shards/NNNNN.offsets.npy        int64 (n + 1,) instance i of the shard owns
                                          points[offsets[i]:offsets[i + 1]]
    CACHE/shards/NNNNN.meta.npz           per-instance columns (see COLUMNS)
    CACHE/eval_shapes/SSSS/<track>.npy    SynthCars ground-truth canonical shapes, for
                                          evaluation only (EvalShapes), never via the cache

Ground-truth shapes are deliberately *not* reachable from :class:`InstanceCache` (it
only has the boolean column ``has_shape``): training code cannot use them by accident;
evaluation opens them explicitly with :class:`EvalShapes`.

Training views built on the cache: PointPnCNet's multi-view groups (20 sequential
observations of a track, four views sampled), per-track multi-frame aggregation in the
track's canonical frame, and TraPCC's Whole-GT / Partial-GT pseudo-ground-truth pools
with the quadrant evenness test.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import zlib
from collections import Counter
from collections.abc import Iterable, Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from pcc_ros import files
from pcc_ros.errors import DataError
from pcc_ros.geometry.boxes import crop_canonical, iou_3d
from pcc_ros.geometry.canonical import from_canonical, to_canonical
from pcc_ros.geometry.partitions import front_back_masks
from pcc_ros.geometry.segments import positions_in_runs
from pcc_ros.types import Boxes, Sample, class_mask

log = logging.getLogger("pcc.extract")

FORMAT = "pcc-instances"
VERSION = 1
SPLITS = ("train", "val", "test")

#: Per-instance columns of ``meta.npz`` (name -> (dtype, trailing shape, meaning)).
COLUMNS: dict[str, tuple[str, tuple[int, ...], str]] = {
    "sequence": ("U", (), "sequence / scene name"),
    "frame": ("int64", (), "frame index inside the sequence"),
    "stamp_ns": ("int64", (), "scan time, ns"),
    "track": ("U", (), "track id ('' when the boxes have none)"),
    "label": ("U", (), "class name"),
    "score": ("float64", (), "box score (1 for ground truth)"),
    "box_center": ("float64", (3,), "box centre, sensor frame, m"),
    "box_size": ("float64", (3,), "length, width, height, m"),
    "box_yaw": ("float64", (), "yaw about +z, sensor frame, rad"),
    "origin": ("float32", (3,), "sensor origin in the canonical frame"),
    "distance": ("float32", (), "sensor-to-box-centre distance, m"),
    "num_points": ("int64", (), "points of the observation"),
    "split": ("U", (), "train / val / test (by track)"),
    "pose": ("float64", (4, 4), "odom <- sensor pose, NaN without poses"),
    "gt_track": ("U", (), "detections mode: track of the best-matching ground-truth box"),
    "gt_iou": ("float32", (), "detections mode: best 3D IoU with a ground-truth box (NaN: none)"),
    "has_shape": ("bool", (), "a SynthCars ground-truth shape exists (see EvalShapes)"),
}


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


def _columns_to_arrays(columns: dict[str, list]) -> dict[str, np.ndarray]:
    out = {}
    for name, (dtype, shape, _) in COLUMNS.items():
        values = columns[name]
        if dtype == "U":
            out[name] = np.array(values, dtype=str) if values else np.zeros(0, dtype="<U1")
        else:
            out[name] = np.array(values, dtype=dtype).reshape((len(values), *shape))
    return out


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
            files.save_npz(shards / f"{name}.meta.npz", **_columns_to_arrays(self.shard.columns))
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
                 "synthcars": None if synth is None else str(synth.root),
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


# --------------------------------------------------------------------------- reading


class InstanceCache:
    """Read-only view of an instance cache: metadata columns in memory, points memory-mapped.

    Attributes:
        root: the cache directory.
        index: the parsed ``index.json``.
        meta: column name -> ``(N, ...)`` array (see :data:`COLUMNS`).
    """

    def __init__(
        self, root: Path, index: dict, meta: dict[str, np.ndarray], shards: list[tuple[np.ndarray, np.ndarray]]
    ) -> None:
        self.root = root
        self.index = index
        self.meta = meta
        self._shards = shards
        sizes = np.array([len(off) - 1 for _, off in shards], dtype=np.int64)
        self._shard_of = np.repeat(np.arange(len(shards)), sizes)
        self._row = positions_in_runs(sizes)

    @classmethod
    def load(cls, path: str | Path, mmap: bool = True) -> InstanceCache:
        """Open a complete cache; :class:`DataError` naming the file when anything is off."""
        root = Path(path)
        index_path = root / "index.json"
        if not index_path.is_file():
            raise DataError(f"{root}: no index.json (not an instance cache; write one with `pcc extract`)")
        try:
            index = json.loads(index_path.read_text())
        except (OSError, ValueError) as exc:
            raise DataError(f"{index_path}: unreadable ({exc})") from exc
        if index.get("format") != FORMAT or index.get("version") != VERSION:
            raise DataError(f"{index_path}: format {index.get('format')} v{index.get('version')}, "
                            f"expected {FORMAT} v{VERSION}")
        if not index.get("complete"):
            raise DataError(f"{root}: extraction did not finish (re-run `pcc extract` to resume)")
        shards, metas = [], []
        for shard in index["shards"]:
            base = root / "shards" / shard["name"]
            try:
                points = np.load(f"{base}.points.npy", mmap_mode="r" if mmap else None, allow_pickle=False)
                offsets = np.load(f"{base}.offsets.npy", allow_pickle=False)
                with np.load(f"{base}.meta.npz", allow_pickle=False) as z:
                    meta = {k: z[k] for k in COLUMNS}
            except (OSError, ValueError, KeyError, EOFError) as exc:
                raise DataError(f"{base}.*: unreadable shard ({exc})") from exc
            n = shard["instances"]
            if (points.ndim != 2 or points.shape[1] != 3 or len(offsets) != n + 1 or offsets[0] != 0
                    or offsets[-1] != len(points) or np.any(np.diff(offsets) < 0)
                    or any(len(v) != n for v in meta.values())):
                raise DataError(f"{base}.*: shard is inconsistent (truncated or corrupt)")
            shards.append((points, offsets))
            metas.append(meta)
        if metas:
            meta = {k: np.concatenate([m[k] for m in metas]) for k in COLUMNS}
        else:
            meta = _columns_to_arrays({k: [] for k in COLUMNS})
        return cls(root, index, meta, shards)

    def __len__(self) -> int:
        return len(self._shard_of)

    def check_finite(self) -> None:
        """:class:`DataError` naming the shard file and the instance when a point is NaN / inf
        (a damaged or hand-edited cache would otherwise surface as a NaN loss much later)."""
        for (points, offsets), shard in zip(self._shards, self.index["shards"]):
            bad = np.flatnonzero(~np.isfinite(points).all(axis=1))
            if len(bad):
                row = int(np.searchsorted(offsets, bad[0], side="right") - 1)
                where = self.root / "shards" / f"{shard['name']}.points.npy"
                raise DataError(f"{where}: instance {row} of the shard has {len(bad)} non-finite point(s)",
                                hint="the cache is damaged; rebuild it with `pcc extract ... --force`")

    def points(self, i: int) -> np.ndarray:
        """Canonical float32 ``(n, 3)`` points of instance ``i`` (a view into the shard)."""
        points, offsets = self._shards[self._shard_of[i]]
        r = self._row[i]
        return points[offsets[r] : offsets[r + 1]]

    def __getattr__(self, name: str) -> np.ndarray:
        meta = self.__dict__.get("meta")
        if meta is not None and name in meta:
            return meta[name]
        raise AttributeError(name)

    @property
    def boxes(self) -> Boxes:
        """All instances' boxes (sensor frame of their scan)."""
        m = self.meta
        return Boxes(m["box_center"], m["box_size"], m["box_yaw"], m["label"], m["score"], m["track"])

    def indices(self, split: str | None = None, min_points: int = 0) -> np.ndarray:
        """Instance indices of ``split`` (``None``: all) with at least ``min_points`` points."""
        keep = self.meta["num_points"] >= min_points
        if split is not None:
            if split not in SPLITS:
                raise DataError(f"unknown split {split!r}; expected one of {SPLITS}")
            keep &= self.meta["split"] == split
        return np.flatnonzero(keep)

    def track_keys(self) -> np.ndarray:
        """``sequence/track`` per instance; instances without a track get a unique key."""
        seq, track = self.meta["sequence"], self.meta["track"]
        own = np.char.add(np.char.add(seq, "/#"), np.arange(len(self)).astype(str))
        return np.where(track != "", np.char.add(np.char.add(seq, "/"), track), own)

    def tracks(self, indices: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """Track key -> its instance indices ordered by frame (optionally within ``indices``)."""
        idx = np.arange(len(self)) if indices is None else np.asarray(indices)
        keys = self.track_keys()[idx]
        order = np.lexsort((self.meta["frame"][idx], keys))
        idx, keys = idx[order], keys[order]
        uniq, starts = np.unique(keys, return_index=True)
        return dict(zip(uniq.tolist(), np.split(idx, starts[1:])))

    def multiview_groups(
        self, indices: np.ndarray | None = None, group_size: int = 20, min_views: int = 4
    ) -> list[np.ndarray]:
        """:func:`multiview_groups` of this cache (what a backend's training recipe calls, so
        ``pcc_ros.models`` needs no import of the data layer)."""
        return multiview_groups(self, indices, group_size, min_views)

    def frame_groups(self, indices: np.ndarray | None = None) -> list[np.ndarray]:
        """Instances grouped by (sequence, frame): the neighbours TraPCC's scene graph needs."""
        idx = np.arange(len(self)) if indices is None else np.asarray(indices)
        keys = np.char.add(np.char.add(self.meta["sequence"][idx], "/"), self.meta["frame"][idx].astype(str))
        order = np.argsort(keys, kind="stable")
        _, starts = np.unique(keys[order], return_index=True)
        return np.split(idx[order], starts[1:])

    def info(self) -> dict:
        """Summary: counts per split, tracks, observations per track, points per observation."""
        n = self.meta["num_points"]
        tracks = self.tracks(np.flatnonzero(self.meta["track"] != ""))
        obs = np.array([len(v) for v in tracks.values()]) if tracks else np.zeros(0, int)
        return {
            "instances": len(self),
            "points": int(n.sum()),
            "splits": {s: int((self.meta["split"] == s).sum()) for s in SPLITS},
            "labels": dict(Counter(self.meta["label"].tolist())),
            "sequences": len(np.unique(self.meta["sequence"])),
            "tracks": len(tracks),
            "observations_per_track": _stats(obs),
            "points_per_observation": _stats(n),
            "with_shape": int(self.meta["has_shape"].sum()),
            "skipped": self.index.get("skipped", {}),
            "config": self.index.get("config", {}),
        }


def _stats(values: np.ndarray) -> dict:
    if len(values) == 0:
        return {"min": 0, "median": 0, "mean": 0.0, "max": 0}
    return {"min": int(values.min()), "median": float(np.median(values)), "mean": float(values.mean()),
            "max": int(values.max())}


class EvalShapes:
    """SynthCars ground-truth shapes of a cache: for evaluation only.

    Kept out of :class:`InstanceCache` and every training dataset on purpose; opening
    this is an explicit act of evaluation code.
    """

    def __init__(self, root: Path) -> None:
        self.root = Path(root) / "eval_shapes"

    @classmethod
    def load(cls, cache_root: str | Path) -> EvalShapes:
        return cls(Path(cache_root))

    def get(self, sequence: str, track: str) -> np.ndarray | None:
        """The canonical float32 ``(M, 3)`` shape of a track, or ``None``."""
        if not track:
            return None
        path = self.root / str(sequence) / f"{track}.npy"
        if not path.exists():
            return None
        try:
            shape = np.load(path, mmap_mode="r", allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise DataError(f"{path}: unreadable shape ({exc})") from exc
        if shape.ndim != 2 or shape.shape[1] != 3:
            raise DataError(f"{path}: expected (M, 3), got {shape.shape}")
        return shape

    def for_instance(self, cache: InstanceCache, i: int) -> np.ndarray | None:
        return self.get(str(cache.meta["sequence"][i]), str(cache.meta["track"][i]))


# --------------------------------------------------------------------------- training views


def multiview_groups(
    cache: InstanceCache, indices: np.ndarray | None = None, group_size: int = 20, min_views: int = 4
) -> list[np.ndarray]:
    """PointPnCNet's groups: each track's observations in frame order, cut into runs of
    ``group_size`` sequential observations; runs shorter than ``min_views`` are dropped
    (a short tail joins the previous run when that keeps it within 1.5 x ``group_size``)."""
    groups: list[np.ndarray] = []
    for key, obs in cache.tracks(indices).items():  # loop over tracks, vectorised inside
        if "/#" in key or len(obs) < min_views:
            continue
        runs = [obs[s : s + group_size] for s in range(0, len(obs), group_size)]
        if len(runs) > 1 and len(runs[-1]) < min_views and len(runs[-2]) + len(runs[-1]) <= 1.5 * group_size:
            tail = runs.pop()
            runs[-1] = np.concatenate([runs[-1], tail])
        groups.extend(r for r in runs if len(r) >= min_views)
    return groups


def sample_views(group: np.ndarray, views: int, rng: np.random.Generator) -> np.ndarray:
    """``views`` distinct observations of a group (the paper samples four of twenty)."""
    if len(group) < views:
        raise DataError(f"group of {len(group)} observations cannot give {views} views")
    return np.sort(rng.choice(group, views, replace=False))


def aggregate_track(cache: InstanceCache, indices: np.ndarray, mode: str = "auto",
                    static_threshold: float = 0.5) -> np.ndarray:
    """Observations of one track merged in the track's canonical frame (float32 ``(M, 3)``).

    ``mode="box"``: every observation is already in its own box's canonical frame, and
    a rigid car's canonical frame is the same in every frame, so the clouds simply
    concatenate; no ego poses needed (moving cars included).
    ``mode="pose"``: observations go sensor -> odom with the frame poses, then into the
    canonical frame of the track's most complete observation: for parked cars whose
    per-frame boxes are noisy, where poses register better than boxes.
    ``mode="auto"``: ``pose`` when every observation has a pose and the box centres in
    odom move less than ``static_threshold`` metres, else ``box``.
    """
    idx = np.asarray(indices)
    if len(idx) == 0:
        return np.zeros((0, 3), np.float32)
    clouds = [cache.points(i) for i in idx]
    poses = cache.meta["pose"][idx]
    has_pose = np.isfinite(poses).all(axis=(1, 2))
    if mode == "auto":
        mode = "box"
        if has_pose.all():
            centres = np.einsum("nij,nj->ni", poses[:, :3, :3], cache.meta["box_center"][idx]) + poses[:, :3, 3]
            if np.linalg.norm(centres - centres.mean(axis=0), axis=1).max() < static_threshold:
                mode = "pose"
    if mode == "box":
        return np.concatenate(clouds).astype(np.float32, copy=False)
    if mode != "pose":
        raise DataError(f"aggregation mode must be auto, box or pose, got {mode!r}")
    if not has_pose.all():
        raise DataError("pose aggregation needs a pose for every observation")
    ref = int(np.argmax([len(c) for c in clouds]))
    r = idx[ref]
    inv_ref = np.linalg.inv(poses[ref])
    out = []
    for k, i in enumerate(idx):  # loop over observations of one track (tens)
        sensor = from_canonical(clouds[k], cache.meta["box_center"][i], cache.meta["box_yaw"][i],
                                cache.meta["box_size"][i, 0])
        moved = sensor @ (inv_ref @ poses[k])[:3, :3].T + (inv_ref @ poses[k])[:3, 3]
        out.append(to_canonical(moved, cache.meta["box_center"][r], cache.meta["box_yaw"][r],
                                cache.meta["box_size"][r, 0]))
    return np.concatenate(out).astype(np.float32)


#: Projections of the evenness test: (name, axis u, axis v) in canonical (x, y, z).
VIEWS = (("side", 0, 2), ("front", 1, 2), ("top", 0, 1))


def evenness(canonical: np.ndarray, cell: float = 0.02, center: tuple[float, float, float] = (0.0, 0.0, 0.0)
             ) -> dict[str, float]:
    """TraPCC's evenness per view: min / max occupied-cell count over the four quadrants.

    Each view projects the cloud onto a plane of the object's axes (side: x-z, front:
    y-z, top: x-y) and samples it evenly on a grid of ``cell`` (canonical units), so a
    dense near side does not outweigh a sparse far side; the quadrants are split at
    ``center``. 1 = perfectly balanced, 0 = a quadrant is empty.
    """
    pts = np.asarray(canonical, dtype=np.float64)[:, :3]
    out = {}
    for name, u, v in VIEWS:
        if len(pts) == 0:
            out[name] = 0.0
            continue
        cells = np.unique(np.floor(pts[:, [u, v]] / cell).astype(np.int64), axis=0)
        mid = (cells + 0.5) * cell
        quadrant = (mid[:, 0] >= center[u]).astype(int) + 2 * (mid[:, 1] >= center[v])
        counts = np.bincount(quadrant, minlength=4)
        out[name] = float(counts.min() / max(counts.max(), 1))
    return out


@dataclass
class PoolEntry:
    """A pseudo-ground-truth cloud: a whole aggregated track, or its front / back half."""

    key: str
    part: str  # "whole", "front" or "back"
    points: np.ndarray
    evenness: dict[str, float]
    instances: np.ndarray


def _pool_tracks(cache: InstanceCache, split: str | None, min_observations: int) -> Iterator[tuple[str, np.ndarray]]:
    for key, obs in cache.tracks(cache.indices(split)).items():
        if "/#" not in key and len(obs) >= min_observations:
            yield key, obs


def whole_gt_pool(cache: InstanceCache, split: str | None = "train", min_points: int = 1024,
                  threshold: float = 0.3, min_observations: int = 2, cell: float = 0.02) -> list[PoolEntry]:
    """TraPCC's Whole-GT pool: aggregated tracks with >= ``min_points`` points whose side,
    front and top projections all pass the evenness test (>= ``threshold``)."""
    pool = []
    for key, obs in _pool_tracks(cache, split, min_observations):
        cloud = aggregate_track(cache, obs)
        if len(cloud) < min_points:
            continue
        score = evenness(cloud, cell)
        if min(score.values()) >= threshold:
            pool.append(PoolEntry(key, "whole", cloud, score, obs))
    return pool


def partial_gt_pool(cache: InstanceCache, split: str | None = "train", min_points: int = 512,
                    threshold: float = 0.3, min_observations: int = 2, cell: float = 0.02) -> list[PoolEntry]:
    """TraPCC's Partial-GT pool: fronts and backs of aggregated tracks, each with
    >= ``min_points`` points and even in its own quadrants (split at the half's centre)."""
    pool = []
    for key, obs in _pool_tracks(cache, split, min_observations):
        cloud = aggregate_track(cache, obs)
        front, back = front_back_masks(cloud)
        for part, mask, cx in (("front", front, 0.25), ("back", back, -0.25)):
            half = cloud[mask]
            if len(half) < min_points:
                continue
            score = evenness(half, cell, center=(cx, 0.0, 0.0))
            if min(score.values()) >= threshold:
                pool.append(PoolEntry(key, part, half, score, obs))
    return pool
