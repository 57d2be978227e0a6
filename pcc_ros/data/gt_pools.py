"""TraPCC's pseudo ground truth: Whole-GT / Partial-GT pools from tracks, and retrieval.

No complete shape is ever used. The pools hold *real scans*: every track of an instance
cache (KITTI tracking, nuScenes, SynthCars, a converted bag with tracked boxes) is
aggregated across its frames in the canonical car frame (each observation is already in
its own box's canonical frame, so the box poses do the motion compensation; see
:func:`~pcc_ros.data.track_aggregate.aggregate_instances`). Then (TraPCC §4.2):

1. **Candidates**: aggregates with at least ``min_points`` (1024) points.
2. **Evenness** (the quadrant test): the aggregate is projected onto the side (x-z),
   front (y-z) and bird's-eye (x-y) planes, sampled evenly on a grid, and each view scores
   ``min / max`` of the occupied-cell counts of its four quadrants
   (:func:`candidate_score`); a candidate's score is the minimum over the
   three views (a car seen from one side only has an empty quadrant in the front and top
   views and scores 0).
3. **Threshold by statistics**: the admission threshold is Otsu's threshold of the
   candidates' own scores (:func:`otsu_threshold`: the cut that maximises the
   between-class variance of the sorted scores, i.e. separates "seen all round" from
   "seen from one side"). It is recomputed from the data every time, recorded in the pool
   metadata, and deterministic; no hand-set constant.
4. The candidates at or above the threshold form the **Whole-GT pool**. Front (x >= 0) and
   back halves of every candidate with at least ``min_half_points`` points are scored the
   same way (quadrants split at the half's own centre) with their own Otsu threshold and
   form the **Partial-GT pool**.

Entries are thinned to an even density (one point per ``thin_cell`` voxel, so a dense
near side does not outweigh the far side) and stored as a seeded subset of at most
``store_points`` points.

**Retrieval** (TraPCC §4.2): for each query observation, the ``size_candidates`` pool
entries with the most similar box (distance of log length / width / height), then among
those the one with the smallest MCD (TraPCC Eq. 2, mean squared distance from each query
point to the entry). Batched: one KD-tree per pool entry, queried once with every query
point that has this entry among its candidates (a loop over entries, not over queries).

**On disk**, next to the instance cache (``CACHE/trapcc_gt/<fingerprint>/``): ``pools.npz``
and ``pools.json`` (thresholds, counts, score distribution), and per queried cache and
split ``assign-<cache fingerprint>-<split>.npz``, written in resumable chunks
(``.partNNNN.npz``) and merged at the end. The fingerprint covers the source caches'
fingerprints, the split and every option: a change rebuilds, a rerun reuses.
"""

from __future__ import annotations

import hashlib
import json
import logging
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial import cKDTree
from tqdm import tqdm

from pcc_ros import files
from pcc_ros.data.track_aggregate import aggregate_instances
from pcc_ros.errors import DataError
from pcc_ros.geometry.partitions import front_back_masks

log = logging.getLogger("pcc.gt_pools")

POOL_VERSION = 1
PARTS = ("whole", "front", "back")
#: Projections of the evenness test: (name, axis u, axis v) in canonical (x, y, z).
VIEWS = (("side", 0, 2), ("front", 1, 2), ("top", 0, 1))
#: Canonical x of each half's centre (the quadrant split of the half's evenness test).
HALF_CENTRE = {"front": 0.25, "back": -0.25}


@dataclass(frozen=True)
class PoolConfig:
    """Options of the pools and the retrieval (all enter the fingerprint)."""

    min_points: int = 1024
    min_half_points: int = 512
    min_observations: int = 2
    cell: float = 0.02
    thin_cell: float = 0.01
    store_points: int = 2048
    store_half_points: int = 1024
    size_candidates: int = 8
    seed: int = 0


# --------------------------------------------------------------------------- statistics


def otsu_threshold(scores: np.ndarray) -> float:
    """Otsu's threshold of a 1-D sample, exactly (no histogram binning).

    Tries every cut between consecutive distinct sorted values and returns the midpoint
    of the cut with the largest between-class variance ``w0 w1 (m0 - m1)^2``. With a
    single distinct value the threshold is that value (everything is admitted).
    """
    s = np.sort(np.asarray(scores, dtype=np.float64).ravel())
    if len(s) == 0:
        raise DataError("otsu_threshold: no scores")
    if s[0] == s[-1]:
        return float(s[0])
    n = len(s)
    csum = np.cumsum(s)
    k = np.arange(1, n)  # class 0 = s[:k]
    valid = s[k - 1] < s[k]  # only cut between distinct values
    w0 = k / n
    m0 = csum[k - 1] / k
    m1 = (csum[-1] - csum[k - 1]) / (n - k)
    between = np.where(valid, w0 * (1 - w0) * (m0 - m1) ** 2, -np.inf)
    best = int(np.argmax(between))
    return float(0.5 * (s[best] + s[best + 1]))


def _cell_keys(coords: np.ndarray, cell: float) -> np.ndarray:
    """One int64 key per grid cell of ``(N, D)`` coordinates (D <= 3; canonical clouds span < 2^20 cells)."""
    ij = np.floor(np.asarray(coords, dtype=np.float64) / cell).astype(np.int64) + (1 << 20)
    key = np.zeros(len(ij), dtype=np.int64)
    for d in range(ij.shape[1]):
        key = (key << 21) | ij[:, d]
    return key


def thin(cloud: np.ndarray, cell: float) -> np.ndarray:
    """One point per ``cell`` voxel (the first in array order): an even density."""
    if len(cloud) == 0 or cell <= 0:
        return cloud
    _, first = np.unique(_cell_keys(cloud, cell), return_index=True)
    return cloud[np.sort(first)]


def _subset(cloud: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    if len(cloud) <= count:
        return cloud
    return cloud[np.sort(rng.choice(len(cloud), count, replace=False))]


def candidate_score(cloud: np.ndarray, cell: float, part: str = "whole") -> tuple[float, dict[str, float]]:
    """TraPCC's evenness score (minimum over side / front / top) and the per-view values.

    Each view projects the cloud onto a plane of the object's axes (side: x-z, front: y-z,
    top: x-y) and counts the occupied cells of a ``cell`` grid (canonical units) in each of
    the four quadrants, split at the part's centre (x = 0, or +-0.25 for a half): counting
    cells rather than points keeps a dense near side from outweighing a sparse far side.
    A view scores ``min / max`` of its quadrant counts: 1 balanced, 0 a quadrant empty.
    """
    center = (HALF_CENTRE.get(part, 0.0), 0.0, 0.0)
    pts = np.asarray(cloud, dtype=np.float64)
    views = {}
    for name, u, v in VIEWS:
        if len(pts) == 0:
            views[name] = 0.0
            continue
        _, first = np.unique(_cell_keys(pts[:, [u, v]], cell), return_index=True)
        cells = np.floor(pts[first][:, [u, v]] / cell)
        mid = (cells + 0.5) * cell
        quadrant = (mid[:, 0] >= center[u]).astype(int) + 2 * (mid[:, 1] >= center[v])
        counts = np.bincount(quadrant, minlength=4)
        views[name] = float(counts.min() / max(counts.max(), 1))
    return float(min(views.values())), views


# --------------------------------------------------------------------------- pools


@dataclass
class Pool:
    """One pool (whole, front or back): fixed-size padded clouds plus their facts."""

    part: str
    points: np.ndarray  # (E, S, 3) float32, rows padded by repetition beyond count
    count: np.ndarray  # (E,) valid points per row
    size: np.ndarray  # (E, 3) median box size (l, w, h) of the track, metres
    key: np.ndarray  # (E,) "source:sequence/track"
    score: np.ndarray  # (E,) evenness score

    def __len__(self) -> int:
        return len(self.count)

    def cloud(self, e: int) -> np.ndarray:
        return self.points[e, : self.count[e]]

    @classmethod
    def empty(cls, part: str, store: int) -> Pool:
        return cls(part, np.zeros((0, store, 3), np.float32), np.zeros(0, np.int64), np.zeros((0, 3)),
                   np.zeros(0, dtype="<U1"), np.zeros(0))

    @classmethod
    def from_entries(cls, part: str, clouds: list[np.ndarray], sizes: list[np.ndarray], keys: list[str],
                     scores: list[float], store: int) -> Pool:
        if not clouds:
            return cls.empty(part, store)
        e = len(clouds)
        points = np.zeros((e, store, 3), np.float32)
        count = np.array([len(c) for c in clouds], dtype=np.int64)
        for i, c in enumerate(clouds):  # loop over pool entries (hundreds)
            points[i] = c[np.arange(store) % len(c)]
        return cls(part, points, count, np.asarray(sizes, dtype=np.float64), np.asarray(keys, dtype=str),
                   np.asarray(scores, dtype=np.float64))


@dataclass
class Pools:
    """The Whole-GT pool and the two halves of the Partial-GT pool, with how they were made."""

    whole: Pool
    front: Pool
    back: Pool
    stats: dict[str, Any] = field(default_factory=dict)

    def part(self, name: str) -> Pool:
        return {"whole": self.whole, "front": self.front, "back": self.back}[name]

    def save(self, folder: Path) -> None:
        folder.mkdir(parents=True, exist_ok=True)
        arrays = {}
        for name in PARTS:
            p = self.part(name)
            arrays.update({f"{name}_points": p.points, f"{name}_count": p.count, f"{name}_size": p.size,
                           f"{name}_key": p.key, f"{name}_score": p.score})
        files.save_npz(folder / "pools.npz", **arrays)
        files.write_json(folder / "pools.json", self.stats, indent=1, sort_keys=True, default=float)

    @classmethod
    def load(cls, folder: Path) -> Pools:
        path = folder / "pools.npz"
        try:
            with np.load(path, allow_pickle=False) as z:
                parts = [Pool(n, z[f"{n}_points"], z[f"{n}_count"], z[f"{n}_size"], z[f"{n}_key"], z[f"{n}_score"])
                         for n in PARTS]
            stats = json.loads((folder / "pools.json").read_text())
        except (OSError, ValueError, KeyError) as exc:
            raise DataError(f"{path}: unreadable GT pools ({exc}); delete the folder to rebuild") from exc
        return cls(*parts, stats=stats)


def track_candidates(cache: Any, split: str | None, config: PoolConfig, source: str = "0",
                     progress: bool = False) -> list[dict[str, Any]]:
    """Aggregated tracks of one cache with their box sizes (before any admission test)."""
    out = []
    tracks = cache.tracks(cache.indices(split))
    for key, obs in tqdm(list(tracks.items()), desc="aggregate tracks", unit="track", disable=not progress,
                         leave=False):
        if "/#" in key or len(obs) < config.min_observations:
            continue
        cloud = aggregate_instances(cache, obs)
        out.append({"key": f"{source}:{key}", "cloud": cloud, "size": np.median(cache.meta["box_size"][obs], axis=0),
                    "observations": len(obs)})
    return out


def build_pools(caches: Sequence[Any], split: str | None, config: PoolConfig | None = None,
                progress: bool = False) -> Pools:
    """The Whole-GT and Partial-GT pools of the tracks of ``split`` in ``caches``."""
    config = config or PoolConfig()
    rng = np.random.default_rng(config.seed)
    tracks = []
    for s, cache in enumerate(caches):
        tracks.extend(track_candidates(cache, split, config, source=str(s), progress=progress))
    stats: dict[str, Any] = {"version": POOL_VERSION, "config": asdict(config), "split": split,
                             "tracks": len(tracks), "threshold_rule": "otsu over the candidates' evenness scores"}
    entries: dict[str, list] = {p: [] for p in PARTS}
    for t in tracks:  # thin once; the halves are cut from the thinned aggregate
        raw = t["cloud"]
        front_raw = raw[:, 0] >= 0
        t["raw_count"] = {"whole": len(raw), "front": int(front_raw.sum()), "back": int((~front_raw).sum())}
        t["thinned"] = thin(raw, config.thin_cell)
    for part in PARTS:
        need = config.min_points if part == "whole" else config.min_half_points
        cands = []
        for t in tracks:  # loop over tracks (hundreds), each vectorised
            if t["raw_count"][part] < need:  # the paper's candidate rule counts the aggregated points
                continue
            cloud = t["thinned"]
            if part != "whole":
                cloud = cloud[cloud[:, 0] >= 0] if part == "front" else cloud[cloud[:, 0] < 0]
            score, views = candidate_score(cloud, config.cell, part)
            cands.append((t, cloud, score, views))
        scores = np.array([c[2] for c in cands])
        threshold = otsu_threshold(scores) if len(cands) else None
        store = config.store_points if part == "whole" else config.store_half_points
        clouds, sizes, keys, kept_scores = [], [], [], []
        for t, cloud, score, _ in cands:
            if score >= threshold:
                clouds.append(_subset(cloud, store, rng).astype(np.float32))
                sizes.append(t["size"])
                keys.append(t["key"])
                kept_scores.append(score)
        entries[part] = [clouds, sizes, keys, kept_scores, store]
        stats[part] = {
            "candidates": len(cands), "admitted": len(clouds), "threshold": threshold,
            "score_quantiles": (np.quantile(scores, [0, 0.25, 0.5, 0.75, 1]).round(4).tolist() if len(cands) else []),
        }
        log.info("GT pool %s: %d of %d candidates admitted (threshold %.3f by Otsu)", part, len(clouds), len(cands),
                 np.nan if threshold is None else threshold)
    pools = [Pool.from_entries(p, *entries[p]) for p in PARTS]
    return Pools(*pools, stats=stats)


# --------------------------------------------------------------------------- retrieval


def size_candidates(query_sizes: np.ndarray, pool_sizes: np.ndarray, k: int) -> np.ndarray:
    """``(Q, min(k, E))`` pool entries with the most similar box (log-size distance), nearest first."""
    q = np.log(np.maximum(np.asarray(query_sizes, dtype=np.float64), 1e-3))
    p = np.log(np.maximum(np.asarray(pool_sizes, dtype=np.float64), 1e-3))
    d = np.linalg.norm(q[:, None, :] - p[None, :, :], axis=2)
    k = min(k, p.shape[0])
    part = np.argpartition(d, k - 1, axis=1)[:, :k]
    order = np.argsort(np.take_along_axis(d, part, axis=1), axis=1, kind="stable")
    return np.take_along_axis(part, order, axis=1)


def retrieve(pool: Pool, clouds: Sequence[np.ndarray], sizes: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Best pool entry of each query cloud: size pre-selection, then the smallest MCD.

    Returns ``(index (Q,), mcd (Q,))``; ``-1`` / NaN for an empty query or an empty pool.
    MCD is TraPCC Eq. 2: mean squared distance from each query point to the entry.
    """
    q = len(clouds)
    best = np.full(q, -1, dtype=np.int64)
    best_mcd = np.full(q, np.nan)
    if q == 0 or len(pool) == 0:
        return best, best_mcd
    lengths = np.array([len(c) for c in clouds], dtype=np.int64)
    nonempty = np.flatnonzero(lengths > 0)
    if len(nonempty) == 0:
        return best, best_mcd
    cand = size_candidates(np.asarray(sizes)[nonempty], pool.size, k)  # (Q', K)
    kk = cand.shape[1]
    offsets = np.concatenate([[0], np.cumsum(lengths)])
    allpts = np.concatenate([np.asarray(c, dtype=np.float64).reshape(-1, 3) for c in clouds])
    mcd = np.full(cand.shape, np.inf)
    flat_q = np.repeat(np.arange(len(nonempty)), kk)
    flat_e = cand.ravel()
    order = np.argsort(flat_e, kind="stable")
    flat_q, flat_e = flat_q[order], flat_e[order]
    slot = order % kk
    entries, starts = np.unique(flat_e, return_index=True)
    bounds = np.append(starts, len(flat_e))
    for j, e in enumerate(entries):  # loop over pool entries; every query of an entry in one tree query
        rows = flat_q[bounds[j] : bounds[j + 1]]
        slots = slot[bounds[j] : bounds[j + 1]]
        qi = nonempty[rows]
        n = lengths[qi]
        point_idx = np.repeat(offsets[qi] - np.concatenate([[0], np.cumsum(n)[:-1]]), n) + np.arange(n.sum())
        d, _ = cKDTree(pool.cloud(int(e))).query(allpts[point_idx], k=1)
        sums = np.bincount(np.repeat(np.arange(len(rows)), n), weights=d * d, minlength=len(rows))
        mcd[rows, slots] = sums / n
    pick = np.argmin(mcd, axis=1)
    best[nonempty] = cand[np.arange(len(nonempty)), pick]
    best_mcd[nonempty] = mcd[np.arange(len(nonempty)), pick]
    return best, best_mcd


def halves(cloud: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """TraPCC's split of a canonical cloud: front (x >= 0) and back (x < 0)."""
    front, back = front_back_masks(cloud)
    return cloud[front], cloud[back]


def assign(pools: Pools, clouds: Sequence[np.ndarray], sizes: np.ndarray, k: int) -> dict[str, np.ndarray]:
    """Whole-GT and front / back Partial-GT of each query (indices into the pools, -1: none)."""
    fronts, backs = zip(*(halves(np.asarray(c)) for c in clouds)) if len(clouds) else ((), ())
    out = {}
    for name, query in (("whole", clouds), ("front", fronts), ("back", backs)):
        idx, mcd = retrieve(pools.part(name), list(query), sizes, k)
        out[f"{name}_index"] = idx
        out[f"{name}_mcd"] = mcd
    return out


# --------------------------------------------------------------------------- cached builds


def _query_subset(cloud: np.ndarray, count: int, seed: int) -> np.ndarray:
    if len(cloud) <= count:
        return cloud
    return cloud[np.sort(np.random.default_rng(seed).choice(len(cloud), count, replace=False))]


def pools_fingerprint(caches: Sequence[Any], split: str | None, config: PoolConfig) -> str:
    payload = {"version": POOL_VERSION, "caches": [c.index.get("fingerprint") for c in caches], "split": split,
               "config": asdict(config)}
    return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()[:16]


def load_or_build_pools(caches: Sequence[Any], split: str | None, root: Path, config: PoolConfig | None = None,
                        progress: bool = True) -> tuple[Pools, Path]:
    """The pools of ``caches`` / ``split``, built once and reused from ``root/<fingerprint>/``."""
    config = config or PoolConfig()
    folder = Path(root) / pools_fingerprint(caches, split, config)
    if (folder / "pools.npz").is_file() and (folder / "pools.json").is_file():
        return Pools.load(folder), folder
    pools = build_pools(caches, split, config, progress=progress)
    pools.stats["sources"] = [str(c.root) for c in caches]
    pools.save(folder)
    return pools, folder


def load_or_assign(pools: Pools, folder: Path, cache: Any, indices: np.ndarray, name: str, k: int,
                   chunk: int = 2048, progress: bool = True, max_query_points: int = 128) -> dict[str, np.ndarray]:
    """The retrieval of ``cache``'s instances ``indices``, resumable in chunks.

    Stored in ``folder/assign-<cache fingerprint>-<name>-...npz`` (``name``: e.g. the split);
    an interrupted run keeps its finished ``.partNNNN.npz`` chunks and continues there.
    The MCD of a query is estimated on a seeded subset of at most ``max_query_points`` of
    its points (the mean over 128 points is a tight estimate; a dense 5000-point crop would
    otherwise cost 40x more for the same choice).
    """
    indices = np.asarray(indices, dtype=np.int64)
    digest = hashlib.sha256(indices.tobytes()).hexdigest()[:8]
    stem = f"assign-{cache.index.get('fingerprint', 'nofp')}-{name}-{digest}-q{max_query_points}"
    final = folder / f"{stem}.npz"
    if final.is_file():
        with np.load(final, allow_pickle=False) as z:
            if np.array_equal(z["indices"], indices):
                return {k2: z[k2] for k2 in z.files}
    parts = []
    starts = range(0, len(indices), chunk)
    for c, start in enumerate(tqdm(starts, desc=f"retrieve GT ({name})", unit="chunk", disable=not progress,
                                   leave=False)):
        part_path = folder / f"{stem}.part{c:04d}.npz"
        sel = indices[start : start + chunk]
        if part_path.is_file():
            with np.load(part_path, allow_pickle=False) as z:
                parts.append({k2: z[k2] for k2 in z.files})
            continue
        clouds = [_query_subset(np.asarray(cache.points(int(i)), dtype=np.float32), max_query_points, int(i))
                  for i in sel]
        result = assign(pools, clouds, cache.meta["box_size"][sel], k)
        result["indices"] = sel
        files.save_npz(part_path, **result)
        parts.append(result)
    keys = ["indices"] + [f"{p}_{s}" for p in PARTS for s in ("index", "mcd")]
    merged = {k2: (np.concatenate([p[k2] for p in parts]) if parts else np.zeros(0)) for k2 in keys}
    merged["indices"] = merged["indices"].astype(np.int64)
    files.save_npz(final, **merged)
    for c in range(len(starts)):
        (folder / f"{stem}.part{c:04d}.npz").unlink(missing_ok=True)
    return merged
