"""The instance cache on disk and its read-only view: what training and evaluation read.

``pcc extract`` (:mod:`pcc_ros.data.instances`) writes it; everything else opens it only
through :class:`InstanceCache`.

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
evaluation opens them explicitly with :class:`EvalShapes`. Multi-frame aggregation of a
track lives in :mod:`pcc_ros.data.track_aggregate`, TraPCC's pseudo-ground-truth pools in
:mod:`pcc_ros.data.gt_pools`.
"""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path

import numpy as np

from pcc_ros.errors import DataError
from pcc_ros.geometry.segments import positions_in_runs
from pcc_ros.types import Boxes

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



def columns_to_arrays(columns: dict[str, list]) -> dict[str, np.ndarray]:
    """Metadata lists (one per column) as the typed arrays ``meta.npz`` stores."""
    out = {}
    for name, (dtype, shape, _) in COLUMNS.items():
        values = columns[name]
        if dtype == "U":
            out[name] = np.array(values, dtype=str) if values else np.zeros(0, dtype="<U1")
        else:
            out[name] = np.array(values, dtype=dtype).reshape((len(values), *shape))
    return out



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
            meta = columns_to_arrays({k: [] for k in COLUMNS})
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

    def track_keys(self, matched: bool = False) -> np.ndarray:
        """``sequence/track`` per instance; instances without a track get a unique key. ``matched``:
        a detection without a track id takes its matched ground-truth track (``gt_track``), the
        association a tracker gives; the training views of a detector-box cache group by it."""
        seq, track = self.meta["sequence"], self.meta["track"]
        if matched:
            track = np.where(track != "", track, self.meta["gt_track"])
        own = np.char.add(np.char.add(seq, "/#"), np.arange(len(self)).astype(str))
        return np.where(track != "", np.char.add(np.char.add(seq, "/"), track), own)

    def tracks(self, indices: np.ndarray | None = None, matched: bool = False) -> dict[str, np.ndarray]:
        """Track key -> its instance indices ordered by frame (optionally within ``indices``;
        ``matched``: see :meth:`track_keys`)."""
        idx = np.arange(len(self)) if indices is None else np.asarray(indices)
        keys = self.track_keys(matched)[idx]
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

    def label_planes(self) -> np.ndarray:
        """``(N, 3)`` per observation: the centre ``x, y`` (canonical units) and the yaw of its labelled
        box in the observation's crop frame, NaN where unknown.

        A crop of a labelled box is its own labelled box (``0, 0, 0``). A crop of a detector's box
        (``pcc extract --boxes detections``) matched to a labelled track (``gt_track``) gets that
        track's box of the same frame, read from the extraction's source (KITTI tracking layout,
        ``label_02``): where the detector's box is offset or turned, the car's centre plane is not
        the crop's x-z plane. Unmatched detections and sources without labels stay NaN. Only boxes
        are read, never a complete shape."""
        out = np.full((len(self), 3), np.nan)
        if self.index.get("config", {}).get("boxes", "ground_truth") != "detections":
            out[:] = 0.0
            return out
        from pcc_ros.data.kitti import KittiTracking  # the extraction's source, read on demand

        matched = np.flatnonzero(self.meta["gt_track"] != "")
        source = self.index.get("source")
        if not len(matched) or not source or not Path(source).is_dir():
            return out
        data = KittiTracking(source)
        for seq in np.unique(self.meta["sequence"][matched]):  # loop over sequences (a few)
            rows = matched[self.meta["sequence"][matched] == seq]
            try:
                labels = data.labels(str(seq), data.calibration(str(seq)))
            except (DataError, OSError) as exc:
                raise DataError(f"{source}: labelled boxes of sequence {seq} unreadable ({exc})") from exc
            if labels is None:
                continue
            for i in rows:  # loop over matched observations, a scalar lookup each
                boxes = labels.get(int(self.meta["frame"][i]))
                hit = np.flatnonzero(boxes.track_id == self.meta["gt_track"][i]) if boxes is not None else []
                if not len(hit):
                    continue
                yaw = float(self.meta["box_yaw"][i])
                c, s = np.cos(yaw), np.sin(yaw)
                d = boxes.center[hit[0], :2] - self.meta["box_center"][i, :2]
                length = float(self.meta["box_size"][i, 0])
                rel = np.angle(np.exp(1j * (float(boxes.yaw[hit[0]]) - yaw)))
                out[i] = [(c * d[0] + s * d[1]) / length, (-s * d[0] + c * d[1]) / length, rel]
        return out

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
    (a short tail joins the previous run when that keeps it within 1.5 x ``group_size``).
    Detections without a track id group by their matched ground-truth track (a tracker's
    association; ``InstanceCache.track_keys(matched=True)``)."""
    groups: list[np.ndarray] = []
    for key, obs in cache.tracks(indices, matched=True).items():  # loop over tracks, vectorised inside
        if "/#" in key or len(obs) < min_views:
            continue
        runs = [obs[s : s + group_size] for s in range(0, len(obs), group_size)]
        if len(runs) > 1 and len(runs[-1]) < min_views and len(runs[-2]) + len(runs[-1]) <= 1.5 * group_size:
            tail = runs.pop()
            runs[-1] = np.concatenate([runs[-1], tail])
        groups.extend(r for r in runs if len(r) >= min_views)
    return groups

