"""Imports point down the flow (docs/ARCHITECTURE.md): read from the source with ``ast``,
every import counted (module level and inside functions alike).

Layers, lowest first — a module may import its own layer and the ones below, never above:

0. base: the shared nouns and helpers (``errors``, ``types``, ``files``, ``paths``, ``scratch``, ``jit``,
   ``tables``, ``assignments``, ``lograte``, the package itself);
1. ``geometry/``: numpy math on boxes and rotations (the one ``box_corners``, the one
   quaternion convention);
2. ``msg/``: ROS messages <-> arrays (markers are drawn from ``geometry.box_corners``, poses
   decoded with ``geometry.rotations`` — so geometry sits under msg, not above it);
3. ``data/`` (with the bag reader and writer, ``data/bag``, ``data/bag_writer``), ``models/``,
   ``metrics/``; ``data`` and ``models`` are siblings that never import each other;
4. ``pipeline/``: config (the parameter table), core, filter;
5. ``runtime/``: the seam, the node logic, pairing, replay over a bag;
6. the doors: ``nodes/``, ``cli/``, ``workflows/`` (``train``, ``evaluate``, ``evaluate_real``,
   ``detection_eval``, ``filter_calibration``, ``filter_sensors``, ``filter_check``, ``demo``).

Also: ``rclpy`` (and the rest of a ROS install: ``rclpy``, ``tf2_ros``, ``rosidl_runtime_py``)
is imported only under ``pcc_ros/nodes/``, and nothing imports ``pcc_ros.cli``.

A module this table does not place fails the test with the line to add: a new module
states where it belongs.
"""

from __future__ import annotations

import ast
import functools
import sys
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "pcc_ros"

LAYER_NAMES = ("base", "geometry", "msg", "data/models", "pipeline", "runtime", "nodes/cli")

#: Exact module names, then prefixes (``"pcc_ros.x."`` covers the package ``x``), to a layer.
EXACT = {
    "pcc_ros": 0,
    "pcc_ros.errors": 0,
    "pcc_ros.types": 0,
    "pcc_ros.files": 0,
    "pcc_ros.scratch": 0,
    "pcc_ros.jit": 0,  # numba compilation of the compiled kernels (filter, networks)
    "pcc_ros.paths": 0,
    "pcc_ros.tables": 0,
    "pcc_ros.assignments": 0,
    "pcc_ros.lograte": 0,  # which occurrences of a repeating warning are logged
    "pcc_ros.plotting": 0,  # matplotlib helpers of the PNGs (box labels)
}
PREFIXES = {
    "pcc_ros.geometry.": 1,
    "pcc_ros.msg.": 2,
    "pcc_ros.data.": 3,
    "pcc_ros.models.": 3,
    "pcc_ros.metrics.": 3,
    "pcc_ros.weights.": 3,
    "pcc_ros.pipeline.": 4,
    "pcc_ros.runtime.": 5,
    "pcc_ros.nodes.": 6,
    "pcc_ros.cli.": 6,
    "pcc_ros.workflows.": 6,  # the libraries of the pcc commands (train, evaluate, demo, ...)
}
#: Sibling folders of one layer that must not import each other.
SIBLINGS = (("pcc_ros.data", "pcc_ros.models"),)

#: Known upward imports, each with why it is not fixed yet. An entry that no longer occurs
#: fails the test too (delete it when its import is gone): the list can only shrink. Empty:
#: the training recipes of models/ get caches, TraPCC's pools and validation from train
#: (models.base.TrainingKit) instead of importing data/ or train.
ALLOWED: set[tuple[str, str]] = set()

ROS_PACKAGES = ("rclpy", "tf2_ros", "rosidl_runtime_py", "launch", "launch_ros")


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def layer(module: str) -> int | None:
    if module in EXACT:
        return EXACT[module]
    for prefix, value in sorted(PREFIXES.items(), key=lambda kv: -len(kv[0])):
        if (module + ".").startswith(prefix):
            return value
    return None


@functools.cache
def imports(path: Path) -> list[tuple[str, int]]:
    """``(imported module, line)`` for every import in the file, relative ones resolved."""
    module = module_name(path)
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    out = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), filename=str(path))):
        if isinstance(node, ast.Import):
            out += [(alias.name, node.lineno) for alias in node.names]
        elif (isinstance(node, ast.Call) and getattr(node.func, "attr", getattr(node.func, "id", "")) == "import_module"
              and node.args and isinstance(node.args[0], ast.Constant) and isinstance(node.args[0].value, str)):
            out.append((node.args[0].value, node.lineno))  # importlib.import_module("rclpy")
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            out.append((target, node.lineno))
            # ``from pcc_ros.x import y`` may import the submodule pcc_ros.x.y
            out += [(f"{target}.{alias.name}", node.lineno) for alias in node.names
                    if (PACKAGE.parent / Path(*f"{target}.{alias.name}".split("."))).with_suffix(".py").is_file()
                    or (PACKAGE.parent / Path(*f"{target}.{alias.name}".split(".")) / "__init__.py").is_file()]
    return out


def sources() -> list[Path]:
    return sorted(PACKAGE.rglob("*.py"))


def upward_imports() -> set[tuple[str, str, int]]:
    """``(importer, imported, line)`` of every import that goes up the flow or across siblings."""
    found = set()
    for path in sources():
        importer = module_name(path)
        low = layer(importer)
        for target, line in imports(path):
            if not target.startswith("pcc_ros") or target == importer:
                continue
            high = layer(target)
            if high is None or low is None:
                continue  # reported by test_every_module_has_a_layer
            across = any(
                ((importer + ".").startswith(a + ".") and (target + ".").startswith(b + "."))
                or ((importer + ".").startswith(b + ".") and (target + ".").startswith(a + "."))
                for a, b in SIBLINGS
            )
            if high > low or across:
                found.add((importer, target, line))
    return found


def test_every_module_has_a_layer():
    unplaced = [module_name(p) for p in sources() if layer(module_name(p)) is None]
    assert not unplaced, (
        f"modules with no layer: {unplaced} — add them to EXACT or PREFIXES in {Path(__file__).name}"
    )


def test_imports_point_down_the_flow():
    found = upward_imports()
    pairs = {(a, b) for a, b, _ in found}
    unexpected = sorted(f"{a} (layer {LAYER_NAMES[layer(a)]}) imports {b} (layer {LAYER_NAMES[layer(b)]}), line {n}"
                        for a, b, n in found if (a, b) not in ALLOWED)
    assert not unexpected, "imports up the flow:\n" + "\n".join(unexpected)
    stale = sorted(ALLOWED - pairs)
    assert not stale, f"allow-listed imports that no longer occur (delete them from ALLOWED): {stale}"


def test_ros_python_only_under_nodes():
    """(Also counts ``importlib.import_module("rclpy")``; this was test_packaging's rclpy test.)"""
    offenders = [
        f"{module_name(p)}:{line} imports {target}"
        for p in sources()
        if not module_name(p).startswith("pcc_ros.nodes.")
        for target, line in imports(p)
        if target.split(".")[0] in ROS_PACKAGES
    ]
    assert not offenders, offenders


def test_nothing_imports_the_cli():
    offenders = [
        f"{module_name(p)}:{line} imports {target}"
        for p in sources()
        if module_name(p) != "pcc_ros.cli" and not module_name(p).startswith("pcc_ros.cli.")
        for target, line in imports(p)
        if target == "pcc_ros.cli" or target.startswith("pcc_ros.cli.")
    ]
    assert not offenders, offenders


def test_the_package_never_imports_the_benchmarks():
    """``benchmarks/`` is not installed: only ``pcc bench`` (cli/bench) loads it, from the checkout's path."""
    offenders = [
        f"{module_name(p)}:{line} imports {target}"
        for p in sources()
        for target, line in imports(p)
        if target.split(".")[0] == "benchmarks"
    ]
    assert not offenders, offenders


def test_tests_import_no_private_names():
    """Tests go through the public API: no ``from pcc_ros.x import _y`` in ``test/``."""
    offenders = [
        f"{path.name}:{node.lineno} imports {alias.name} from {node.module}"
        for path in sorted(Path(__file__).parent.glob("*.py"))
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8")))
        if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("pcc_ros")
        for alias in node.names
        if alias.name.startswith("_")
    ]
    assert not offenders, offenders


#: Library imports of another module's private name still to go, each with why. An entry
#: that no longer occurs fails the test (the list can only shrink).
PRIVATE_ALLOWED: set[tuple[str, str, str]] = set()


def private_imports(package: Path) -> set[tuple[str, str, str]]:
    """``(importer, module, name)`` of every ``from pcc_ros.x import _y`` (relative too) in
    ``package`` where ``_y`` is private (one leading underscore; dunders such as
    ``__version__`` are public) and ``x`` is another module."""
    found = set()
    for path in sorted(package.rglob("*.py")):
        importer = ".".join(path.relative_to(package.parent).with_suffix("").parts)
        importer = importer.removesuffix(".__init__")
        base = importer if path.name == "__init__.py" else importer.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), filename=str(path))):
            if not isinstance(node, ast.ImportFrom):
                continue
            if node.level:
                parts = base.split(".")[: len(base.split(".")) - (node.level - 1)]
                target = ".".join(parts + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if not target.startswith("pcc_ros") or target == importer:
                continue
            found |= {(importer, target, a.name) for a in node.names
                      if a.name.startswith("_") and not (a.name.startswith("__") and a.name.endswith("__"))}
    return found


def test_library_imports_no_private_names():
    """A module's ``_name`` is its own: another module of pcc_ros that needs it uses a public
    name of the home module (``tables.metric_cell``, ``files.write_json``, ``data.kitti.split_dir``,
    ``pipeline.filter.local_ground``), so the house keeps one public copy of each helper."""
    found = private_imports(PACKAGE)
    unexpected = sorted(f"{a} imports {n} from {b}" for a, b, n in found - PRIVATE_ALLOWED)
    assert not unexpected, "private names imported from another module:\n" + "\n".join(unexpected)
    stale = sorted(PRIVATE_ALLOWED - found)
    assert not stale, f"allow-listed private imports that no longer occur (delete them): {stale}"


def test_the_private_import_check_sees_one(tmp_path):
    package = tmp_path / "pcc_ros"
    (package / "geometry").mkdir(parents=True)
    (package / "__init__.py").write_text("__version__ = '1'\n")
    (package / "geometry" / "__init__.py").write_text("")
    (package / "geometry" / "a.py").write_text("def _h():\n    return 1\n")
    (package / "geometry" / "b.py").write_text(
        "from pcc_ros import __version__\nfrom .a import _h\n\ndef f():\n    from pcc_ros.geometry.a import _h, g\n"
    )
    assert private_imports(package) == {("pcc_ros.geometry.b", "pcc_ros.geometry.a", "_h")}


def test_the_checker_sees_a_violation(tmp_path, monkeypatch):
    """The scan is not vacuous: an upward import and a function-level rclpy import are found."""
    package = tmp_path / "pcc_ros"
    (package / "geometry").mkdir(parents=True)
    (package / "__init__.py").write_text("")
    (package / "geometry" / "__init__.py").write_text("")
    (package / "geometry" / "bad.py").write_text(
        "from pcc_ros.pipeline import core\n\ndef f():\n    from ..runtime.node import X\n    import rclpy\n"
        "    importlib.import_module('rclpy.node')\n"
    )
    monkeypatch.setattr(sys.modules[__name__], "PACKAGE", package)
    assert {(a, b) for a, b, _ in upward_imports()} == {
        ("pcc_ros.geometry.bad", "pcc_ros.pipeline"), ("pcc_ros.geometry.bad", "pcc_ros.runtime.node")
    }
    assert [t for t, _ in imports(package / "geometry" / "bad.py")][-2:] == ["rclpy", "rclpy.node"]
