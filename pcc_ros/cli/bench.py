"""Run one benchmark of the source checkout's benchmarks/ folder and print its table.

Benchmarks are developer tools, not part of the installed package: they live in the
top-level ``benchmarks/`` folder of a source checkout (``make bench`` runs them all and
writes ``benchmarks/results/``). ``pcc bench NAME`` finds that folder beside the
``pcc_ros`` package it runs from (an editable install, or ``python -m pcc_ros.cli`` in the
checkout) and says so when there is none (a wheel or colcon install).
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
from pathlib import Path
from types import ModuleType

import pcc_ros
from pcc_ros.errors import ConfigError

#: Where the benchmarks are in a source checkout: beside the ``pcc_ros`` package.
BENCHMARKS = Path(pcc_ros.__file__).resolve().parents[1] / "benchmarks"


def benchmarks_package() -> ModuleType | None:
    """The checkout's ``benchmarks`` package (imported once), or ``None`` outside a checkout."""
    loaded = sys.modules.get("benchmarks")
    if loaded is not None and Path(loaded.__file__).resolve().parent == BENCHMARKS:
        return loaded
    init = BENCHMARKS / "__init__.py"
    if not init.is_file():
        return None
    spec = importlib.util.spec_from_file_location("benchmarks", init, submodule_search_locations=[str(BENCHMARKS)])
    module = importlib.util.module_from_spec(spec)
    sys.modules["benchmarks"] = module
    spec.loader.exec_module(module)
    return module


def add_arguments(parser: argparse.ArgumentParser) -> None:
    package = benchmarks_package()
    if package is not None:
        package.add_arguments(parser)
        return
    parser.add_argument("bench_name", nargs="?", metavar="NAME", help="(needs a source checkout)")
    parser.add_argument("passthrough", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)


def run(args: argparse.Namespace) -> int:
    package = benchmarks_package()
    if package is None:
        raise ConfigError(
            f"{BENCHMARKS}: no benchmarks here - pcc bench runs from a source checkout of pcc_ros "
            "(benchmarks/ is not installed); clone the repository and run `make bench` or `pcc bench NAME` there"
        )
    return package.run(args)
