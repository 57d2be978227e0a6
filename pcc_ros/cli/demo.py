"""``pcc demo``: the whole product on a SynthCars sequence, then on real KITTI frames.

The command half of :mod:`pcc_ros.workflows.demo`: the flags and the :class:`~pcc_ros.workflows.demo.DemoConfig`
built from them.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from pcc_ros.workflows.demo import DemoConfig, demo


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, default=Path("out/demo"), help="output folder (default out/demo)")
    parser.add_argument("--backend", help="completion backend (default: the shipped config's)")
    parser.add_argument("--checkpoint", help="checkpoint of the backend (default: shipped weights)")
    parser.add_argument("--frames", type=int, default=10, help="SynthCars frames per sequence (default 10)")
    parser.add_argument("--seed", type=int, default=2026, help="SynthCars seed (default 2026)")
    parser.add_argument("--kitti", type=Path, help="KITTI tracking root (default: ../shared/data/kitti_tracking)")
    parser.add_argument("--baselines", default="input,mirror",
                        help="baselines shown beside the backend (default input,mirror)")


def run(args: argparse.Namespace) -> int:
    opts = DemoConfig(out=args.out, backend=args.backend, checkpoint=args.checkpoint, frames=args.frames,
                      seed=args.seed, kitti=args.kitti, baselines=args.baselines)
    results = demo(opts)
    print(f"\nwrote {opts.out / 'demo.json'} and the PNGs: "
          + ", ".join(r["png"] for r in (results["synthcars"], results["kitti"]) if r))
    return 0
