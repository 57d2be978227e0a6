"""Extract canonical car instances from a bag, KITTI or nuScenes into an instance cache.

Examples::

    pcc extract ../shared/data/kitti_tracking --out cache/kitti
    pcc extract synthcars/ --out cache/synth --boxes detections --min-points 20
    pcc extract --info cache/kitti            # summary + cache/kitti/info.png

Re-running with the same inputs and options does nothing; an interrupted run resumes;
other inputs or options need ``--force``. See docs/instances.md for the cache format.
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

import numpy as np

from pcc_ros.data.instances import ExtractConfig, InstanceCache, extract_instances
from pcc_ros.data.sources import count_frames, open_frames
from pcc_ros.errors import ConfigError
from pcc_ros.pipeline.config import PipelineConfig

log = logging.getLogger("pcc.extract")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("source", type=Path, nargs="?",
                        help="bag, KITTI tracking/object dir, nuScenes root or SynthCars dir")
    parser.add_argument("--out", type=Path, help="instance cache directory to write")
    parser.add_argument("--info", type=Path, metavar="CACHE", help="summarise an existing cache (and write info.png)")
    parser.add_argument("--classes", default="Car,Van", help="comma-separated classes (default Car,Van)")
    parser.add_argument("--min-points", type=int, default=10, help="drop observations with fewer points (default 10)")
    parser.add_argument("--boxes", choices=("ground_truth", "detections"), default="ground_truth",
                        help="crop ground-truth boxes or detector boxes (default ground_truth)")
    parser.add_argument("--detections-dir", type=Path, help="KITTI detections folder (bags carry their own)")
    parser.add_argument("--sequence", help="only this KITTI sequence / nuScenes scene")
    parser.add_argument("--margin", type=float, default=0.0, help="box margin, metres (default 0)")
    parser.add_argument("--ground-margin", type=float, default=0.1,
                        help="drop points this close above the box bottom (ground returns), metres (default 0.1)")
    parser.add_argument("--node-crop", action="store_true",
                        help="crop as completion_node does: its box_margin and ground_margin (the pipeline "
                             "defaults) instead of --margin / --ground-margin; training inputs then look like the "
                             "node's")
    parser.add_argument("--val-fraction", type=float, default=0.1, help="share of tracks in val (default 0.1)")
    parser.add_argument("--test-fraction", type=float, default=0.2,
                        help="share of tracks in test (default 0.2; SynthCars uses its own test sequences)")
    parser.add_argument("--synthcars", type=Path, help="SynthCars root for splits and eval shapes (default: SOURCE)")
    parser.add_argument("--force", action="store_true", help="rebuild a cache made from other inputs / options")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    if args.info is not None:
        return show_info(args.info)
    if args.source is None or args.out is None:
        raise ConfigError("pcc extract needs SOURCE and --out (or --info CACHE)")
    for name in ("val_fraction", "test_fraction"):
        if not 0.0 <= getattr(args, name) < 1.0:
            raise ConfigError(f"--{name.replace('_', '-')} must be in [0, 1)")
    if args.val_fraction + args.test_fraction >= 1.0:
        raise ConfigError("--val-fraction + --test-fraction must be < 1")
    if args.min_points < 1:
        raise ConfigError("--min-points must be >= 1")

    classes = tuple(c.strip() for c in args.classes.split(",") if c.strip())
    if not classes:
        raise ConfigError("--classes is empty")
    margin, ground_margin = args.margin, args.ground_margin
    if args.node_crop:
        node = PipelineConfig()
        margin, ground_margin = float(node.box_margin), float(node.ground_margin)
    config = ExtractConfig(classes=classes, min_points=args.min_points, boxes=args.boxes, margin=margin,
                           ground_margin=ground_margin, val_fraction=args.val_fraction,
                           test_fraction=args.test_fraction)
    frames = open_frames(args.source, sequence=args.sequence, detections_dir=args.detections_dir)
    total = None if args.no_progress else count_frames(args.source, args.sequence)  # the bar's total and ETA
    cache = extract_instances(frames, args.out, config, source=args.source, synthcars=args.synthcars,
                              force=args.force, progress=not args.no_progress, total=total)
    info = cache.info()
    log.info("%s: %d instances of %d tracks (%s)", args.out, info["instances"], info["tracks"],
             ", ".join(f"{k} {v}" for k, v in info["splits"].items()))
    return 0


def show_info(path: Path) -> int:
    """Print the cache summary as JSON and write ``info.png`` next to the index."""
    cache = InstanceCache.load(path)
    info = cache.info()
    print(json.dumps(info, indent=1, sort_keys=True))
    png = write_info_png(cache, path / "info.png")
    print(f"plot: {png}")
    return 0


def write_info_png(cache, out: Path) -> Path:
    """Histograms of points per observation (log bins), observations per track, distance."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(14, 4))
    n = cache.meta["num_points"]
    if len(n):
        bins = np.logspace(0, np.log10(max(n.max(), 10)) + 0.05, 30)
        for split in ("train", "val", "test"):
            sel = cache.meta["split"] == split
            if sel.any():
                axes[0].hist(n[sel], bins=bins, alpha=0.6, label=f"{split} ({sel.sum()})")
        axes[0].set_xscale("log")
        axes[0].legend()
    axes[0].set(title="points per observation", xlabel="points", ylabel="observations")
    tracks = cache.tracks(np.flatnonzero(cache.meta["track"] != ""))
    obs = [len(v) for v in tracks.values()]
    if obs:
        axes[1].hist(obs, bins=np.arange(1, max(obs) + 2) - 0.5)
    axes[1].set(title=f"observations per track ({len(obs)} tracks)", xlabel="observations", ylabel="tracks")
    if len(n):
        axes[2].scatter(cache.meta["distance"], n, s=4, alpha=0.5)
        axes[2].set_yscale("log")
    axes[2].set(title="points vs distance", xlabel="distance to sensor (m)", ylabel="points")
    fig.suptitle(f"{cache.root}: {len(cache)} observations")
    fig.tight_layout()
    fig.savefig(out, dpi=90)
    plt.close(fig)
    return out
