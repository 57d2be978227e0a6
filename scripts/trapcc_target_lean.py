"""Where TraPCC's lean to the seen flank comes from: the signed lateral mean (toward the sensor's side
positive, canonical units: metres / box length) of each training observation's input, of the pseudo
ground truth retrieved for it (the raw Whole-GT entry, the front / back Partial-GT halves), of the
labelled box's centre in a detector-box crop, and of a checkpoint's coarse and detailed outputs on a
sample of the same observations, per training cache.

    python scripts/trapcc_target_lean.py --data CACHE --checkpoint W [--option KEY=VALUE ...]

``--data`` and ``--option`` as ``pcc train trapcc`` takes them (the same caches, pools and options
the run trained with, e.g. ``scripts/gpu_train.sh``'s); the output is one JSON line per cache. A
target that leans with the input teaches the network the lean; 0 is a car centred on its box.
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import torch

from pcc_ros.models.registry import get_backend
from pcc_ros.workflows.train import load_recipe, parse_options


def mean_y(pool, index: np.ndarray) -> np.ndarray:
    """Mean y of each assigned pool entry (NaN where none is assigned)."""
    out = np.full(len(index), np.nan)
    ok = index >= 0
    if not ok.any():
        return out
    pts, count = pool.points[index[ok]], pool.count[index[ok]]
    valid = np.arange(pts.shape[1])[None] < count[:, None]
    out[ok] = (pts[..., 1] * valid).sum(1) / count
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", required=True, help="the training cache (pcc train --data)")
    parser.add_argument("--checkpoint", default="pcc_ros/weights/trapcc.safetensors")
    parser.add_argument("--option", action="append", default=[], help="KEY=VALUE as pcc train takes it")
    parser.add_argument("--split", default="train")
    parser.add_argument("--sample", type=int, default=256, help="observations per cache run through the network")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    torch.manual_seed(args.seed)
    options = {**parse_options(args.option), "input_dropout": 0.0}  # the inputs as the node gives them
    recipe = load_recipe("trapcc", "default", options)
    main_cache = recipe.open_data(args.data)
    data = recipe.training_data(main_cache, args.split)
    caches = [main_cache, *(recipe.kit.open_cache(p) for p in recipe.options.real_data)]
    names, side, label_y = [], [], []
    for summary, cache in zip(data.summary["sources"], caches):  # the order training_data added them in
        rows = cache.indices(args.split, min_points=10)
        if summary["instances"] != len(rows):  # training_data left out observations without a Whole-GT
            raise SystemExit(f"{cache.root}: {len(rows) - summary['instances']} observations had no Whole-GT; "
                             "this script needs every one assigned")
        names += [str(cache.root).rstrip("/").split("/")[-1]] * len(rows)
        side.append(np.sign(np.asarray(cache.meta["origin"])[rows, 1]))
        label_y.append(cache.label_planes()[rows, 1])
    names, side, label_y = np.array(names), np.concatenate(side), np.concatenate(label_y)
    inputs = np.array([c[:, 1].mean() for c in data.clouds])
    whole = mean_y(data.pools.whole, data.whole)
    front, back = mean_y(data.pools.front, data.front), mean_y(data.pools.back, data.back)
    completer = get_backend("trapcc").from_checkpoint(args.checkpoint, device="cpu")
    net, cfg = completer.model.eval(), dict(completer.config)
    rng = np.random.default_rng(args.seed)
    detailed, coarse = np.full(len(data), np.nan), np.full(len(data), np.nan)
    for name in np.unique(names):  # a sample per cache, batches of 32
        ids = rng.permutation(np.flatnonzero(names == name))[: args.sample]
        for k in range(0, len(ids), 32):
            batch = recipe.make_batch(data, ids[k : k + 32], cfg, rng)
            with torch.no_grad():
                out = net(batch.points, batch.segment, batch.batch_size, batch.neighbours)
            detailed[ids[k : k + 32]] = out["detailed"][..., 1].mean(1).numpy()
            if "coarse" in out:
                coarse[ids[k : k + 32]] = out["coarse"][..., 1].mean((1, 2)).numpy()

    def signed(values: np.ndarray, mask: np.ndarray) -> float | None:
        v = side[mask] * values[mask]
        return round(float(np.nanmean(v)), 4) if np.isfinite(v).any() else None

    for name in np.unique(names):
        m = names == name
        print(json.dumps({"cache": name, "observations": int(m.sum()),
                          "seen_from_left": round(float((side[m] > 0).mean()), 3),
                          "input": signed(inputs, m), "whole_gt_raw": signed(whole, m), "front_gt": signed(front, m),
                          "back_gt": signed(back, m), "labelled_centre": signed(label_y, m),
                          "output_coarse": signed(coarse, m), "output_detailed": signed(detailed, m)}))


if __name__ == "__main__":
    main()
