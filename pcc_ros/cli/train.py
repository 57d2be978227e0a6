"""Train a completion backend self-supervised from partial scans (``pcc train BACKEND``).

The command half of :mod:`pcc_ros.workflows.train`: the flags, the :class:`~pcc_ros.workflows.train.TrainConfig`
built from them, and the summary printed by rank 0.
"""

from __future__ import annotations

import argparse
import contextlib
import json
from pathlib import Path

from pcc_ros.workflows.train import Distributed, TrainConfig, parse_options, train


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("backend", help="backend to train (e.g. pointpncnet)")
    parser.add_argument("--data", type=Path, required=True, help="instance cache written by `pcc extract`")
    parser.add_argument("--out", type=Path, required=True, help="output directory (checkpoints, log, PNG)")
    parser.add_argument("--config", default="default", help="model size preset: default | paper")
    parser.add_argument("--iterations", type=int, default=4000, help="optimizer steps in total (default 4000)")
    parser.add_argument("--batch-size", type=int, default=32, help="instances (groups) per step and process")
    parser.add_argument("--lr", type=float, default=None, help="learning rate (default: the backend's, 5e-4)")
    parser.add_argument(
        "--lr-decay-every", type=int, default=None,
        help="halve the learning rate every N steps (default: a quarter of --iterations, the paper's ratio)",
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of the initial weights and of batch sampling")
    parser.add_argument("--resume", action="store_true", help="continue from OUT/resume.safetensors")
    parser.add_argument("--no-inpainting", action="store_true", help="ablation: no synthetic region removal")
    parser.add_argument("--stage", default=None, help="training stage of a multi-stage backend (aml: prior | encoder)")
    parser.add_argument(
        "--option", action="append", default=[], metavar="KEY=VALUE",
        help="backend training option (JSON value), e.g. --option views=2 (repeatable)",
    )
    parser.add_argument("--device", default="auto", help="auto | cpu | cuda[:N] (under torchrun: cuda:LOCAL_RANK)")
    parser.add_argument("--split", default="train", help="training split of the cache (default train)")
    parser.add_argument("--val-split", default="val", help="validation split (default val)")
    parser.add_argument("--val-instances", type=int, default=200, help="validation subset size (default 200)")
    parser.add_argument("--val-every", type=int, default=500, help="validate every N steps (0: only at the end)")
    parser.add_argument("--checkpoint-every", type=int, default=250, help="write the resume checkpoint every N steps")
    parser.add_argument("--min-points", type=int, default=10, help="skip training observations with fewer points")
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's)")
    parser.add_argument("--no-progress", action="store_true", help="no tqdm bar (log lines only)")
    parser.add_argument(
        "--real-data", type=Path, action="append", default=[], metavar="CACHE",
        help="instance cache of real scans mixed into training, all its splits (repeatable)",
    )
    parser.add_argument(
        "--real-share", type=float, default=0.1,
        help="share of training groups drawn from --real-data (default 0.1; the few real groups are repeated)",
    )
    parser.add_argument(
        "--init", type=Path, metavar="CHECKPOINT",
        help="start from these weights (e.g. the shipped checkpoint; fresh optimizer), recorded in the config",
    )
    parser.add_argument(
        "--max-minutes", type=float, default=None, metavar="M",
        help="wall-clock budget: stop the loop after M minutes, then validate and save as at the end",
    )
    parser.add_argument(
        "--select-by", choices=("cd_l1", "fscore", "coverage"), default="cd_l1",
        help="validation metric that picks the shipped weights (best, not last; default cd_l1)",
    )


def train_config(args: argparse.Namespace) -> TrainConfig:
    """The :class:`TrainConfig` of ``pcc train``'s parsed flags."""
    return TrainConfig(
        backend=args.backend, data=args.data, out=args.out, size=args.config, iterations=args.iterations,
        batch_size=args.batch_size, lr=args.lr, lr_decay_every=args.lr_decay_every, seed=args.seed,
        resume=args.resume, inpainting=not args.no_inpainting, stage=args.stage, options=parse_options(args.option),
        device=args.device, split=args.split, val_split=args.val_split, val_instances=args.val_instances,
        val_every=args.val_every, checkpoint_every=args.checkpoint_every, min_points=args.min_points,
        threads=args.threads, progress=not args.no_progress, real_data=list(args.real_data),
        real_share=args.real_share, init=args.init, select_by=args.select_by, max_minutes=args.max_minutes,
    )


def run(args: argparse.Namespace) -> int:
    with contextlib.suppress(BrokenPipeError):
        summary = train(train_config(args))
        if Distributed.from_env().main:
            print(json.dumps(summary, indent=2))
    return 0
