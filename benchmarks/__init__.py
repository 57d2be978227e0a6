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
import os
import pkgutil
import shlex
import subprocess
import time
from pathlib import Path

from pcc_ros.cli.text import plain_text


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


#: Other processes' average CPU use (cores) up to which a run counts as on an idle machine (the
#: load average cannot tell: it counts the benchmark's own threads, and the previous one's).
IDLE_CORES = 0.1
#: Environment variables that change the timings (threads, OpenMP's spin: ``pcc_ros.GOMP_SPINCOUNT``).
TIMING_ENVIRONMENT = ("OMP_NUM_THREADS", "GOMP_SPINCOUNT", "OMP_WAIT_POLICY", "MKL_NUM_THREADS")


def run_context() -> dict[str, object]:
    """When, on which commit and with which timing-relevant environment a benchmark ran (its JSON
    records it, so a README figure can be traced to its run)."""
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=Path(__file__).parent,
                                capture_output=True, text=True, timeout=5).stdout.strip() or None
    except (OSError, subprocess.SubprocessError):
        commit = None
    return {"utc": time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime()), "commit": commit,
            "environment": {k: os.environ.get(k) for k in TIMING_ENVIRONMENT}}


def _without_output(argv: list[str]) -> list[str]:
    """A benchmark's arguments without ``--json FILE``: the command as a reader reruns it."""
    out, skip = [], False
    for arg in argv:
        if skip:
            skip = False
        elif arg == "--json":
            skip = True
        elif not arg.startswith("--json="):
            out.append(arg)
    return out


def run(args: argparse.Namespace) -> int:
    module = importlib.import_module(f"{__name__}.{args.bench_name}")
    bench_args = benchmark_parser(args.bench_name, module).parse_args(args.passthrough)
    context = run_context()
    context["command"] = shlex.join(["pcc", "bench", args.bench_name, *_without_output(args.passthrough)])
    from benchmarks.common import OtherLoad

    with OtherLoad() as others:
        results = module.run(bench_args)
    if others.cores is not None:
        context["other_processes_cores"] = round(others.cores, 3)
        verdict = ("NOT idle: absolute times are inflated; the ratios are interleaved" if others.cores > IDLE_CORES
                   else "idle")
        print(f"other processes used {others.cores:.2f} of {os.cpu_count()} cores on average during this run "
              f"(/proc/stat: the machine's busy time minus this process's): {verdict}")
    results = {**results, "run": context} if isinstance(results, dict) else results
    if bench_args.json:
        bench_args.json.parent.mkdir(parents=True, exist_ok=True)
        from pcc_ros.files import write_json

        write_json(bench_args.json, results, indent=2, sort_keys=True)
    return 0
