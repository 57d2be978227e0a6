"""Copy an instance cache with every observation thinned to at most N points (a seeded subset).

Why: a training run on a lent machine receives a small folder (tens of MiB), and a near car's
crop holds thousands of returns that training never reads in full (PointPnCNet caps its input
at 512 points and each pseudo-ground-truth view at ``loss_points``; TraPCC at 256 / 384). The
thinned copy keeps every observation, its metadata and the evaluation shapes of the tracks kept
(``--shape-tracks``: at most that many tracks' shapes, seeded; the others' ``has_shape`` cleared,
so evaluation and validation skip nothing silently). Its fingerprint records the thinning, so
pools and retrievals cached from the full cache are not mistaken for this one's.

    python scripts/thin_cache.py FULL_CACHE OUT_CACHE --max-points 512 [--seed 0] [--shape-tracks 40]
        [--shape-split val]
"""

from __future__ import annotations

import argparse
import hashlib
import json
import shutil
from pathlib import Path

import numpy as np

from pcc_ros.data.instance_cache import InstanceCache


def thin(src: Path, dst: Path, max_points: int, seed: int, shape_tracks: int | None,
         shape_split: str | None = None) -> dict:
    """Write the thinned copy of ``src`` to ``dst``; returns its summary."""
    cache = InstanceCache.load(src, mmap=True)
    index = json.loads((src / "index.json").read_text())
    if dst.exists():
        shutil.rmtree(dst)
    (dst / "shards").mkdir(parents=True)
    keep_shapes: set[tuple[str, str]] | None = None
    shapes_dir = src / "eval_shapes"
    if shapes_dir.is_dir():
        available = sorted((p.parent.name, p.stem) for p in shapes_dir.glob("*/*.npy"))
        if shape_split is not None:  # only the tracks that split's observations belong to
            sel = cache.meta["split"] == shape_split
            wanted = set(zip(cache.meta["sequence"][sel].tolist(), cache.meta["track"][sel].tolist()))
            available = [a for a in available if a in wanted]
        if shape_tracks is not None and len(available) > shape_tracks:
            pick = np.random.default_rng(seed).choice(len(available), shape_tracks, replace=False)
            available = [available[i] for i in sorted(pick)]
        keep_shapes = set(available)
        for seq, track in keep_shapes:
            (dst / "eval_shapes" / seq).mkdir(parents=True, exist_ok=True)
            shutil.copy2(shapes_dir / seq / f"{track}.npy", dst / "eval_shapes" / seq / f"{track}.npy")
    start = 0
    total_in = total_out = 0
    for shard in index["shards"]:
        base = src / "shards" / shard["name"]
        with np.load(f"{base}.meta.npz", allow_pickle=False) as z:
            meta = {k: z[k] for k in z.files}
        offsets = np.load(f"{base}.offsets.npy")
        points = np.load(f"{base}.points.npy", mmap_mode="r")
        n = len(offsets) - 1
        parts, counts = [], np.diff(offsets)
        for j in range(n):  # loop over observations (thousands); the subset is one vectorised choice
            cloud = np.asarray(points[offsets[j]:offsets[j + 1]])
            if len(cloud) > max_points:
                rng = np.random.default_rng([seed, start + j])
                cloud = cloud[np.sort(rng.choice(len(cloud), max_points, replace=False))]
            parts.append(cloud)
        new_counts = np.array([len(p) for p in parts], dtype=np.int64)
        new_offsets = np.concatenate([[0], np.cumsum(new_counts)]).astype(offsets.dtype)
        np.save(dst / "shards" / f"{shard['name']}.points.npy",
                np.concatenate(parts).astype(np.float32) if parts else np.zeros((0, 3), np.float32))
        np.save(dst / "shards" / f"{shard['name']}.offsets.npy", new_offsets)
        meta["num_points"] = new_counts
        if keep_shapes is not None and "has_shape" in meta:
            meta["has_shape"] = np.array([bool(h) and (str(s), str(t)) in keep_shapes for h, s, t in
                                          zip(meta["has_shape"], meta["sequence"], meta["track"])])
        np.savez_compressed(dst / "shards" / f"{shard['name']}.meta.npz", **meta)
        shard["points"] = int(new_counts.sum())
        total_in += int(counts.sum())
        total_out += int(new_counts.sum())
        start += n
    stamp = f"{index.get('fingerprint')}|thin{max_points}|seed{seed}|shapes{shape_tracks}"
    index["fingerprint"] = hashlib.sha256(stamp.encode()).hexdigest()[:32]
    index["thinned"] = {"from": str(src), "max_points": max_points, "seed": seed, "shape_tracks": shape_tracks,
                        "points_before": total_in, "points_after": total_out}
    (dst / "index.json").write_text(json.dumps(index, indent=1, sort_keys=True))
    InstanceCache.load(dst)  # the copy opens as a cache
    return {"instances": len(cache), **index["thinned"],
            "shapes": None if keep_shapes is None else len(keep_shapes)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("src", type=Path)
    parser.add_argument("dst", type=Path)
    parser.add_argument("--max-points", type=int, default=512)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--shape-tracks", type=int, default=None, help="keep at most this many tracks' eval shapes")
    parser.add_argument("--shape-split", default=None, help="keep only the eval shapes of this split's tracks")
    args = parser.parse_args()
    print(json.dumps(thin(args.src, args.dst, args.max_points, args.seed, args.shape_tracks, args.shape_split)))


if __name__ == "__main__":
    main()
