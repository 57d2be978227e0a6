"""One copy of each idea (docs/ARCHITECTURE.md): the helpers that had copies stay single.

Read from the source with ``ast``: quaternion helpers are defined only in
``geometry/rotations.py``, box-corner functions only in ``geometry/boxes.py``, box-local transforms (a box's centre
and yaw: ``to_box_local``) only in ``geometry/canonical.py``, and files are
renamed into place (``os.replace`` / ``os.rename`` / ``Path.rename``) only by
``pcc_ros/files.py`` (files) and ``data/bag_writer.atomic_bag`` (bag directories); which
occurrences of a repeating warning are logged is decided only by ``lograte.worth_logging``.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "pcc_ros"

HOMES = {"quaternion": "geometry/rotations.py", "corners": "geometry/boxes.py", "box_local": "geometry/canonical.py"}
RENAMERS = {"files.py", "data/bag_writer.py"}


def _trees():
    for path in sorted(PACKAGE.rglob("*.py")):
        yield path.relative_to(PACKAGE).as_posix(), ast.parse(path.read_text(encoding="utf-8"))


def test_quaternion_and_corner_helpers_have_one_home():
    misplaced = [
        f"{name}:{node.lineno} defines {node.name} (its home is {home})"
        for name, tree in _trees()
        for node in ast.walk(tree)
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef)
        for word, home in HOMES.items()
        if word in node.name.lower() and name != home
    ]
    assert not misplaced, misplaced


def test_files_are_renamed_into_place_only_by_the_atomic_writers():
    renames = [
        f"{name}:{node.lineno}"
        for name, tree in _trees()
        if name not in RENAMERS
        for node in ast.walk(tree)
        if isinstance(node, ast.Call) and getattr(node.func, "attr", "") in ("replace", "rename")
        and isinstance(node.func, ast.Attribute)
        and (getattr(node.func.value, "id", "") == "os" or node.func.attr == "rename")
    ]
    assert not renames, f"write through pcc_ros.files (atomic_write, write_json, save_npz ...): {renames}"


def test_repeating_warnings_are_rate_limited_only_by_lograte():
    """The 1st / 10th / 100th rule was written out twice (``str(n).rstrip("0") == "1"``) and a
    first-then-every-100th rule (``n % 100 == 1``) twice more: ``lograte.worth_logging`` says both."""
    spelled = re.compile(r"""rstrip\(["']0["']\)\s*==|%\s*10+\s*==\s*1\b""")
    # n % 100 == 1 and the like, not an odd-number test such as n % 2 == 1
    found = [f"{path.relative_to(PACKAGE)}:{number}: {line.strip()}"
             for path in sorted(PACKAGE.rglob("*.py")) if path.name != "lograte.py"
             for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1) if spelled.search(line)]
    assert not found, f"use pcc_ros.lograte.worth_logging: {found}"


def test_worth_logging_counts_powers_of_ten_or_every_nth():
    from pcc_ros.lograte import worth_logging

    assert [n for n in range(1, 2001) if worth_logging(n)] == [1, 10, 100, 1000]
    assert [n for n in range(1, 302) if worth_logging(n, every=100)] == [1, 101, 201, 301]
    # a count that jumps: any occurrence to log in (previous, count]
    assert worth_logging(12, previous=8) and not worth_logging(99, previous=12) and worth_logging(150, previous=99)
    assert worth_logging(3, previous=0) and not worth_logging(5, previous=5) and not worth_logging(0)
    assert worth_logging(105, previous=99, every=100) and not worth_logging(200, previous=101, every=100)
