"""One copy of each idea (docs/ARCHITECTURE.md): the helpers that had copies stay single.

Read from the source with ``ast``: quaternion helpers are defined only in
``geometry/rotations.py``, box-corner functions only in ``geometry/boxes.py``, box-local transforms (a box's centre
and yaw: ``to_box_local``) only in ``geometry/canonical.py``, and files are
renamed into place (``os.replace`` / ``os.rename`` / ``Path.rename``) only by
``pcc_ros/files.py`` (files) and ``data/bag_writer.atomic_bag`` (bag directories).
"""

from __future__ import annotations

import ast
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
