"""docs/ARCHITECTURE.md's folder map is checked against the tree: every module of the package
appears in it, and every module it lists exists."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "pcc_ros"


def _without_parentheses(text: str) -> str:
    while True:
        stripped = re.sub(r"\([^()]*\)", "", text)
        if stripped == text:
            return text
        text = stripped


def mapped_modules(markdown: str) -> set[str]:
    """``folder/module`` of every module the folder map lists (root modules as ``module``)."""
    section = markdown[markdown.index("## Folder map"):]
    block = section[section.index("```") + 3:]
    block = block[: block.index("```")]
    lines = block.split("\n")
    entries: list[list[str]] = []  # [folder ("" for root lines), text], continuation lines joined
    for line in lines[lines.index("pcc_ros/") + 1:]:
        if line and not line.startswith(" "):
            break  # the next top-level folder (benchmarks/ ...): the package is done
        entry = re.match(r"^  (\S+)(.*)$", line)
        if entry:
            first, content = entry.groups()
            entries.append([first, content] if first.endswith("/") else ["", line])
        elif entries:
            entries[-1][1] += " " + line.strip()
    out: set[str] = set()
    for folder, text in entries:
        if not folder:
            out |= set(re.findall(r"(\w+)\.py\b", text))
        elif any((PACKAGE / folder).glob("*.py")):  # weights/ holds no modules
            out |= {f"{folder}{item.split()[0]}" for item in _without_parentheses(text).split("·") if item.split()}
    return out


def tree_modules() -> set[str]:
    return {p.relative_to(PACKAGE).with_suffix("").as_posix() for p in PACKAGE.rglob("*.py")
            if p.name != "__init__.py"}


def test_folder_map_lists_every_module_and_only_existing_ones():
    mapped = mapped_modules((ROOT / "docs" / "ARCHITECTURE.md").read_text(encoding="utf-8"))
    tree = tree_modules()
    assert not tree - mapped, f"add to docs/ARCHITECTURE.md's folder map: {sorted(tree - mapped)}"
    assert not mapped - tree, f"in docs/ARCHITECTURE.md's folder map, not in pcc_ros/: {sorted(mapped - tree)}"


def test_the_map_parser_sees_a_missing_and_a_stale_entry():
    text = (ROOT / "docs" / "ARCHITECTURE.md").read_text(encoding="utf-8")
    assert "geometry/voxels" in mapped_modules(text) and "workflows/train" in mapped_modules(text)
    edited = text.replace(" · voxels (AML's grids)", " · voxel_grids (AML's grids)", 1)
    mapped = mapped_modules(edited)
    assert "geometry/voxels" not in mapped and "geometry/voxel_grids" in mapped


#: The house rule: a module longer than this is split by concern (docs/ARCHITECTURE.md).
MAX_LINES = 600


def long_modules(package: Path, limit: int = MAX_LINES) -> dict[str, int]:
    """``folder/module.py`` -> line count of every module of ``package`` over ``limit`` lines."""
    counts = {p.relative_to(package).as_posix(): len(p.read_text(encoding="utf-8").splitlines())
              for p in package.rglob("*.py")}
    return {name: n for name, n in sorted(counts.items()) if n > limit}


def test_no_module_is_over_the_line_limit():
    assert not long_modules(PACKAGE), f"split by concern (at most {MAX_LINES} lines): {long_modules(PACKAGE)}"


def test_the_line_limit_sees_a_long_module(tmp_path):
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "long.py").write_text("x = 1\n" * (MAX_LINES + 1))
    (tmp_path / "short.py").write_text("x = 1\n" * MAX_LINES)
    assert long_modules(tmp_path) == {"sub/long.py": MAX_LINES + 1}
