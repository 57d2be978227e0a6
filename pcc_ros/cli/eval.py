"""Evaluate completion backends on an instance cache, or on real labelled frames (``pcc eval``).

The command half of :mod:`pcc_ros.workflows.evaluate` (and of :mod:`pcc_ros.workflows.evaluate_real` with
``--real``): the flags, the :class:`~pcc_ros.workflows.evaluate.EvalConfig` (with ``--real``:
:class:`~pcc_ros.workflows.evaluate_real.RealEvalConfig`) built from them, and the tables printed.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from pcc_ros.errors import ConfigError
from pcc_ros.models.checkpoint import checkpoint_paths
from pcc_ros.workflows.evaluate import EvalConfig, evaluate_cache, parse_checkpoints, print_tables
from pcc_ros.workflows.evaluate_real import RealEvalConfig, run_real


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", type=Path, help="instance cache written by `pcc extract` (not with --real)")
    parser.add_argument(
        "--real", action="store_true",
        help="real-data evaluation: KITTI tracking / nuScenes / Argoverse 2 frames with labels, each track's crops "
        "aggregated as its partial ground truth (see pcc_ros/metrics/realdata.py)",
    )
    parser.add_argument(
        "--real-sources", default="../shared/data/kitti_tracking,../shared/data/nuscenes_mini",
        help="--real: comma-separated KITTI tracking / object, nuScenes roots or Argoverse 2 logs / split dirs "
        "(default: the shared samples of a development checkout; docs/datasets.md 'Getting real data')",
    )
    parser.add_argument("--real-voxel", type=float, default=0.03, help="--real: reference voxel size, metres")
    parser.add_argument(
        "--real-min-points", type=int, default=None,
        help="--real: inputs with fewer points are skipped (default: completion_node's min_points)",
    )
    parser.add_argument(
        "--real-detections", default=None, metavar="DIR",
        help="--real: crop the inputs from these detector results (KITTI label format with scores), each matched "
        "to a labelled track by 3D IoU >= 0.5, instead of the labelled boxes",
    )
    parser.add_argument(
        "--real-matched-labels", action="store_true",
        help="--real with --real-detections: crop the labelled box of each matched detection instead (the same "
        "observations as the detector rows, with the labels' boxes: separates the detector's box errors from "
        "which cars it finds)",
    )
    parser.add_argument(
        "--real-mirror", action="store_true",
        help="--real: reflect every frame across the sensor's x-z plane first (points, labels, detections), so "
        "each car is seen from its other flank: a backend that favours one side of the box frame is not rewarded "
        "for the side the tracks happen to be seen from",
    )
    parser.add_argument(
        "--real-generated-only", action="store_true",
        help="--real: score learned backends' generated points only (default: the published, partial-preserving "
        "output, plus a NAME/generated row)",
    )
    parser.add_argument(
        "--real-table", type=Path, default=None, metavar="PATH",
        help="--real: write the summary (completeness, generated-only completeness, unseen half, lateral balance, "
        "consistency per backend) as a Markdown table, the README's real-data table",
    )
    parser.add_argument(
        "--real-track-memory", choices=("ids", "nearest"), default=None,
        help="--real: track-level completion as completion_node's track_memory does it: each car completed from "
        "its crops of the earlier frames too (causal), associated by the labels' track ids or by the nearest box",
    )
    parser.add_argument(
        "--plot-backends", default=None,
        help="--real: comma-separated completion columns of the PNG (default: every evaluated backend)",
    )
    parser.add_argument("--split", default="test", help="split to evaluate (default: test)")
    parser.add_argument(
        "--backends", default=None,
        help="comma-separated backends (default: the baselines; with --real every available backend)",
    )
    parser.add_argument(
        "--checkpoint", action="append", default=[], metavar="NAME=PATH",
        help="checkpoint of a learned backend (repeatable); default: the shipped one",
    )
    parser.add_argument("--device", default="auto", help="auto | cpu | cuda[:N] for learned backends")
    parser.add_argument("--batch-size", type=int, default=32, help="completion batch size of learned backends")
    parser.add_argument("--json", type=Path, help="write the results here")
    parser.add_argument("--plot", type=Path, help="PNG grid of examples (input / completions / reference)")
    parser.add_argument(
        "--reference", choices=("auto", "ground_truth", "aggregated"), default="auto",
        help="what completions are scored against (auto: SynthCars shapes when the cache has them)",
    )
    parser.add_argument(
        "--min-track-frames", type=int, default=2,
        help="aggregated reference: observations a track needs (default 2)",
    )
    parser.add_argument("--max-instances", type=int, help="evaluate a seeded random subset of this size")
    parser.add_argument("--seed", type=int, default=0, help="subset and EMD subsample seed (default 0)")
    parser.add_argument("--fixed-threshold", type=float, default=0.05, help="fixed F-score threshold, metres")
    parser.add_argument("--emd-points", type=int, default=1024, help="EMD subsample size (exact assignment)")
    parser.add_argument("--no-emd", action="store_true", help="skip EMD (the slowest metric)")
    parser.add_argument(
        "--decode-density", type=int, default=None,
        help="folding decoders decode N times finer per grid axis (default: 1; with --real, completion_node's "
        "decode_density)",
    )
    parser.add_argument(
        "--keep-input", action="store_true",
        help="score the partial-preserving output (observed crop + generated points, what completion_node "
        "publishes) instead of the generated points alone",
    )
    parser.add_argument("--examples", type=int, default=4, help="rows in the example grid")
    parser.add_argument(
        "--no-gt-free", action="store_true",
        help="skip TraPCC's L-G / L-S / meanCD (no pseudo-GT pools built from the cache's train tracks)",
    )
    parser.add_argument(
        "--no-resume", action="store_true",
        help="recompute every backend even if --json already holds results for the same instances and settings",
    )


def refuse_writing_over_checkpoints(checkpoints: dict[str, Path], outputs: dict[str, Path | None]) -> None:
    """An output named like a checkpoint's file (``--json out/trapcc.json`` beside
    ``--checkpoint trapcc=out/trapcc.safetensors``) would silently replace the checkpoint's config,
    which records its weights' hash and training: refused before anything runs."""
    for flag, out in outputs.items():
        if out is None:
            continue
        for name, checkpoint in checkpoints.items():
            if out.resolve() in {p.resolve() for p in checkpoint_paths(checkpoint)}:
                raise ConfigError(f"{flag} {out} is a file of the {name} checkpoint ({checkpoint}): "
                                  "choose another output path")


def run(args: argparse.Namespace) -> int:
    refuse_writing_over_checkpoints(parse_checkpoints(args.checkpoint), {"--json": args.json, "--plot": args.plot})
    if args.real:
        return run_real(RealEvalConfig(
            sources=[Path(s.strip()) for s in args.real_sources.split(",") if s.strip()], backends=args.backends,
            checkpoints=parse_checkpoints(args.checkpoint), voxel=args.real_voxel, min_points=args.real_min_points,
            min_track_frames=args.min_track_frames,
            detections=Path(args.real_detections) if args.real_detections else None,
            matched_labels=args.real_matched_labels, keep_input=not args.real_generated_only,
            decode_density=args.decode_density, device=args.device,
            batch_size=args.batch_size, json=args.json, plot=args.plot, plot_backends=args.plot_backends,
            examples=args.examples, table=args.real_table, track_memory=args.real_track_memory,
            mirror=args.real_mirror,
        ))
    if args.data is None:
        raise ConfigError("--data is required (an instance cache), unless --real")
    opts = EvalConfig(
        data=args.data, split=args.split, backends=args.backends, checkpoints=parse_checkpoints(args.checkpoint),
        device=args.device, batch_size=args.batch_size, json=args.json, plot=args.plot, reference=args.reference,
        min_track_frames=args.min_track_frames, max_instances=args.max_instances, seed=args.seed,
        fixed_threshold=args.fixed_threshold, emd_points=args.emd_points, with_emd=not args.no_emd,
        examples=args.examples, gt_free=not args.no_gt_free, resume=not args.no_resume, keep_input=args.keep_input,
        decode_density=args.decode_density or 1,
    )
    results, reference = evaluate_cache(opts)
    print_tables(results, reference)
    return 0
