"""Real completions from three views (side / front / top), one row per car, one block per backend.

Used for the real-data figure of docs/trapcc.md::

    python scripts/trapcc_views.py out/cache_kitti_det out/cache_kitti out/cache_kobj out/cache_nusc \\
        --backends trapcc,pointpncnet --rows 8 --out docs/img/trapcc_real_views.png

Instances are the observations of the given instance caches (``pcc extract``), spread over
their point counts (sparse and dense); with ``--min-score`` detections below that score
(mapped with ``--sigmoid`` for logit scores) are left out. Context-using backends (TraPCC)
get the other instances of the same frame as scene-graph neighbours, as online. Canonical
frame: x forward, y left, z up, box length 1. Red: the partial input; blue: the completion.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

VIEWS = (("side (x-z)", 0, 2), ("front (y-z)", 1, 2), ("top (x-y)", 0, 1))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("caches", nargs="+", type=Path, help="instance caches (pcc extract)")
    parser.add_argument("--backends", default="trapcc", help="comma-separated backends")
    parser.add_argument("--checkpoint", action="append", default=[], metavar="NAME=PATH")
    parser.add_argument("--rows", type=int, default=8, help="cars shown")
    parser.add_argument("--min-points", type=int, default=30, help="cars with fewer input points are not shown")
    parser.add_argument("--min-score", type=float, default=None, help="drop detections under this score")
    parser.add_argument("--sigmoid", action="store_true", help="scores are logits (PointRCNN)")
    parser.add_argument("--out", type=Path, required=True, help="PNG path")
    parser.add_argument("--json", type=Path, help="also write the picked instances and figures here")
    args = parser.parse_args()

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from pcc_ros.data.instance_cache import InstanceCache
    from pcc_ros.models import load_completer
    from pcc_ros.workflows.evaluate import EvalInstance, attach_contexts, instance_sizes, parse_checkpoints

    picked = []
    for path in args.caches:
        cache = InstanceCache.load(path)
        score = cache.meta["score"].astype(float)
        if args.sigmoid:
            score = 1.0 / (1.0 + np.exp(-score))
        keep = cache.meta["num_points"] >= args.min_points
        if args.min_score is not None:
            keep &= score >= args.min_score
        insts = [
            EvalInstance(key=f"{path.name}:{cache.meta['sequence'][i]}/{cache.meta['frame'][i]}/"
                         f"{cache.meta['track'][i] or i}", partial=np.asarray(cache.points(int(i)), np.float32),
                         reference=np.zeros((1, 3), np.float32), length=float(cache.meta["box_size"][i, 0]),
                         distance=float(cache.meta["distance"][i]), has_ground_truth=False, meta={"index": int(i)},
                         size=np.asarray(cache.meta["box_size"][i], np.float64))
            for i in np.flatnonzero(keep)
        ]
        attach_contexts(cache, insts)
        picked.extend(insts)
    if not picked:
        raise SystemExit("no instances to show")
    order = np.argsort([p.num_points for p in picked], kind="stable")
    rows = [picked[int(order[i])] for i in np.linspace(0, len(order) - 1, min(args.rows, len(order))).round()
            .astype(int)]
    rows = list({r.key: r for r in rows}.values())
    backends = [b.strip() for b in args.backends.split(",") if b.strip()]
    checkpoints = parse_checkpoints(args.checkpoint)
    outputs = {}
    for name in backends:
        completer = load_completer(name, checkpoints.get(name), device="cpu")
        contexts = [r.context for r in rows] if getattr(completer, "uses_context", False) else None
        # the generated points, made with the boxes' sizes as in the node (the red input is drawn over them)
        outputs[name] = completer.complete([r.partial for r in rows], contexts, sizes=instance_sizes(rows))

    cols = len(backends) * len(VIEWS)
    fig, axes = plt.subplots(len(rows), cols, figsize=(2.3 * cols, 1.9 * len(rows)), squeeze=False)
    for r, inst in enumerate(rows):
        for b, name in enumerate(backends):
            out = outputs[name][r]
            for v, (title, u, w) in enumerate(VIEWS):
                ax = axes[r, b * len(VIEWS) + v]
                ax.scatter(out[:, u], out[:, w], s=0.6, c="tab:blue", linewidths=0)
                ax.scatter(inst.partial[:, u], inst.partial[:, w], s=1.2, c="tab:red", linewidths=0)
                ax.set_xlim(-0.65, 0.65)
                ax.set_ylim(-0.4 if w == 2 else -0.45, 0.4 if w == 2 else 0.45)
                ax.set_aspect("equal")
                ax.set_xticks([])
                ax.set_yticks([])
                if r == 0:
                    ax.set_title(f"{name}: {title}", fontsize=8)
                if b == 0 and v == 0:
                    ax.set_ylabel(f"{inst.key}\n{inst.num_points} pts, {inst.distance:.0f} m", fontsize=6)
    fig.suptitle("real scans: input (red) and completion (blue), canonical frame (box length 1)", fontsize=9)
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=110)
    if args.json:
        args.json.write_text(json.dumps({"rows": [{"key": r.key, "points": r.num_points,
                                                   "neighbours": 0 if r.context is None else
                                                   len(r.context.neighbour_boxes)} for r in rows]}, indent=1))
    print(f"wrote {args.out} ({len(rows)} cars x {len(backends)} backends)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
