"""``pcc bench NAME``: benchmarks, each a module of this package.

A benchmark module exposes ``add_arguments(parser)`` (optional) and
``run(args) -> dict``; it prints its own table (ratios against a baseline measured in
the same process) and returns the JSON-able results, which ``--json FILE`` writes.
Speed targets are checked here, never by timed unit tests.

Benchmark modules are imported only when their benchmark runs (their one-line help is
read from the source), so ``pcc --help`` stays fast and one benchmark's heavy imports
never slow down, or break, the others.
"""

from __future__ import annotations

import argparse
import ast
import importlib
import importlib.util
import pkgutil
from pathlib import Path

from pcc_ros.tables import plain_text


def available() -> list[str]:
    """Benchmark names: every module of this package except the shared helpers."""
    return sorted(
        m.name for m in pkgutil.iter_modules(__path__) if not m.name.startswith("_") and m.name != "common"
    )


def _summary(name: str) -> str:
    spec = importlib.util.find_spec(f"{__name__}.{name}")
    doc = ast.get_docstring(ast.parse(Path(spec.origin).read_text())) if spec and spec.origin else None
    return (doc or name).strip().splitlines()[0]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="bench_name", metavar="NAME", required=True)
    for name in available():
        p = sub.add_parser(name, help=_summary(name), add_help=False)
        p.add_argument("passthrough", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)


def benchmark_parser(name: str, module) -> argparse.ArgumentParser:
    """The full parser of one benchmark (common options plus the module's own)."""
    parser = argparse.ArgumentParser(  # the docstring's own paragraphs and lists, as written
        prog=f"pcc bench {name}", description=plain_text((module.__doc__ or name).strip()),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--json", type=Path, help="write the results to this JSON file")
    parser.add_argument("--seed", type=int, default=0, help="random seed")
    if hasattr(module, "add_arguments"):
        module.add_arguments(parser)
    return parser


def run(args: argparse.Namespace) -> int:
    module = importlib.import_module(f"{__name__}.{args.bench_name}")
    bench_args = benchmark_parser(args.bench_name, module).parse_args(args.passthrough)
    results = module.run(bench_args)
    if bench_args.json:
        bench_args.json.parent.mkdir(parents=True, exist_ok=True)
        from pcc_ros.files import write_json

        write_json(bench_args.json, results, indent=2, sort_keys=True)
    return 0
