"""Real vs simulated car crops, side by side: where does SynthCars differ from real scans?

Statistics per crop (sensor frame, from an instance cache: canonical points moved back with
their box):

* points against range (the sensor's angular resolution, dropouts, occlusion);
* vertical distribution: height above the box bottom as a fraction of the box height, pooled
  with equal weight per crop (ground returns, roof / glass dropouts, floating bodies);
* ring structure: distinct beam elevations hitting the car against range (beam pattern);
* surface thickness: per point, distance to the plane of its 8 nearest neighbours (range
  noise and mixed pixels at edges thicken a real surface).

``python -m pcc_ros.data.domain_gap --real CACHE [CACHE ...] --sim CACHE [--sim-after CACHE] --out gap.png``
writes the plot and prints the medians; with ``--sim-after`` the simulator before and after a
change are drawn against the same real crops.
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from pcc_ros.data.instance_cache import InstanceCache
from pcc_ros.files import write_json
from pcc_ros.geometry.canonical import from_canonical

log = logging.getLogger("pcc.gap")

#: Elevation difference that separates two beams, degrees (HDL-64E: >= 0.33 deg apart).
RING_GAP_DEG = 0.15


def crop_stats(cache: Any, max_instances: int = 2000, seed: int = 0) -> dict[str, np.ndarray]:
    """Per-crop statistics of an instance cache (a seeded subset of at most ``max_instances``)."""
    n = len(cache)
    idx = np.arange(n) if n <= max_instances else np.sort(np.random.default_rng(seed).choice(n, max_instances, False))
    meta = cache.meta
    dist, npts, rings, thick = [], [], [], []
    heights = []
    for i in idx:  # loop over crops; each crop's points are vectorised
        can = np.asarray(cache.points(int(i)), dtype=np.float64)
        size = meta["box_size"][i]
        pts = from_canonical(can, meta["box_center"][i], float(meta["box_yaw"][i]), float(size[0]))
        dist.append(float(meta["distance"][i]))
        npts.append(len(pts))
        el = np.sort(np.degrees(np.arctan2(pts[:, 2], np.hypot(pts[:, 0], pts[:, 1]))))
        rings.append(int(1 + np.sum(np.diff(el) > RING_GAP_DEG)) if len(el) else 0)
        h = (can[:, 2] * size[0] + size[2] / 2) / size[2]
        heights.append(np.histogram(h, bins=20, range=(0.0, 1.0))[0] / max(len(h), 1))
        if len(pts) >= 10:
            _, nn = cKDTree(pts).query(pts, k=9)
            nb = pts[nn] - pts[nn].mean(axis=1, keepdims=True)
            # smallest singular value / sqrt(k): RMS distance to the local plane
            sv = np.linalg.svd(nb, compute_uv=False)[:, -1] / 3.0
            thick.append(float(np.median(sv)))
        else:
            thick.append(np.nan)
    return {"distance": np.array(dist), "points": np.array(npts), "rings": np.array(rings),
            "thickness": np.array(thick), "height_hist": np.array(heights)}


def summary(stats: dict[str, np.ndarray]) -> dict[str, Any]:
    """Medians per distance band, and the pooled vertical histogram's lowest / highest tenth."""
    out: dict[str, Any] = {"crops": len(stats["distance"])}
    for lo, hi in ((0, 15), (15, 30), (30, 80)):
        m = (stats["distance"] >= lo) & (stats["distance"] < hi)
        if m.any():
            out[f"{lo}-{hi}m"] = {
                "crops": int(m.sum()),
                "points": float(np.median(stats["points"][m])),
                "rings": float(np.median(stats["rings"][m])),
                "thickness_mm": float(1e3 * np.nanmedian(stats["thickness"][m])),
            }
    hist = stats["height_hist"].mean(axis=0)
    out["share_lowest_10pct_height"] = float(hist[:2].sum())
    out["share_highest_10pct_height"] = float(hist[-2:].sum())
    return out


def plot(named: dict[str, dict[str, np.ndarray]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 4, figsize=(18, 4.2))
    colours = {"real": "tab:red", "sim (before)": "tab:blue", "sim (after)": "tab:green"}
    for name, s in named.items():
        c = colours.get(name, None)
        axes[0].scatter(s["distance"], s["points"], s=4, alpha=0.35 if name != "real" else 0.9, c=c, label=name)
        axes[1].plot((np.arange(20) + 0.5) / 20, s["height_hist"].mean(axis=0), marker="o", ms=3, c=c, label=name)
        axes[2].scatter(s["distance"], s["rings"], s=4, alpha=0.35 if name != "real" else 0.9, c=c, label=name)
        axes[3].scatter(s["distance"], 1e3 * s["thickness"], s=4, alpha=0.35 if name != "real" else 0.9, c=c,
                        label=name)
    axes[0].set(xlabel="range to box centre [m]", ylabel="points in the box", yscale="log", title="points vs range")
    axes[1].set(xlabel="height above box bottom / box height", ylabel="share of a crop's points",
                title="vertical distribution (mean over crops)")
    axes[2].set(xlabel="range [m]", ylabel="distinct beams on the car", title="ring structure")
    axes[3].set(xlabel="range [m]", ylabel="median RMS to local plane [mm]", yscale="log",
                title="surface thickness (noise, mixed pixels)")
    for ax in axes:
        ax.legend(fontsize=8)
        ax.grid(alpha=0.3)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m pcc_ros.data.domain_gap", description=__doc__.splitlines()[0])
    parser.add_argument("--real", type=Path, nargs="+", required=True, help="instance caches of real scans")
    parser.add_argument("--sim", type=Path, required=True, help="instance cache of SynthCars (before)")
    parser.add_argument("--sim-after", type=Path, help="instance cache of SynthCars after a simulator change")
    parser.add_argument("--out", type=Path, required=True, help="PNG to write (JSON beside it)")
    parser.add_argument("--max-instances", type=int, default=1500)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    real_parts = [crop_stats(InstanceCache.load(p), args.max_instances) for p in args.real]
    named = {"real": {k: np.concatenate([r[k] for r in real_parts]) for k in real_parts[0]},
             "sim (before)": crop_stats(InstanceCache.load(args.sim), args.max_instances)}
    if args.sim_after:
        named["sim (after)"] = crop_stats(InstanceCache.load(args.sim_after), args.max_instances)
    plot(named, args.out)
    report = {name: summary(s) for name, s in named.items()}

    write_json(args.out.with_suffix(".json"), report, indent=1)
    print(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
