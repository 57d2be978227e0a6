"""``pcc bench NAME``: benchmarks, each a module of this package.

A benchmark module exposes ``add_arguments(parser)`` (optional) and
``run(args) -> dict``; it prints its own table (ratios against a baseline measured in
the same process) and returns the JSON-able results, which ``--json FILE`` writes.
Speed targets are checked here, never by timed unit tests.
"""

from __future__ import annotations

import argparse
import importlib
import json
import pkgutil
from pathlib import Path


def available() -> list[str]:
    """Benchmark names: every module of this package except the shared helpers."""
    return sorted(
        m.name for m in pkgutil.iter_modules(__path__) if not m.name.startswith("_") and m.name != "common"
    )


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="bench_name", metavar="NAME", required=True)
    for name in available():
        module = importlib.import_module(f"{__name__}.{name}")
        p = sub.add_parser(name, help=(module.__doc__ or name).strip().splitlines()[0])
        p.add_argument("--json", type=Path, help="write the results to this JSON file")
        p.add_argument("--seed", type=int, default=0, help="random seed")
        if hasattr(module, "add_arguments"):
            module.add_arguments(p)


def run(args: argparse.Namespace) -> int:
    module = importlib.import_module(f"{__name__}.{args.bench_name}")
    results = module.run(args)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(results, indent=2, sort_keys=True) + "\n")
    return 0
