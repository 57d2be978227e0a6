"""Say which dataset layout a folder holds and what it lacks, before a long conversion (``pcc check-data``).

Examples::

    pcc check-data data/kitti_tracking        # KITTI tracking layout — complete; sequences, scans
    pcc check-data data/av2/sensor/val        # AV2 split: logs, and what each lacks
    pcc check-data ../shared/data             # a folder of datasets: each one

Exit status 0 when every root is a complete layout, 1 otherwise (the report says what is
missing and where the data comes from).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from pcc_ros.data.layouts import check_tree


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("roots", type=Path, nargs="+", metavar="ROOT",
                        help="dataset folder: KITTI tracking / object, nuScenes root, Argoverse 2 log or split")


def run(args: argparse.Namespace) -> int:
    reports = [r for root in args.roots for r in check_tree(root)]
    for report in reports:
        print("\n".join(report.lines()))
    return 0 if all(r.ok for r in reports) else 1
