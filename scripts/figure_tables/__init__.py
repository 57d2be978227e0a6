"""The renderers of the figure blocks of the README and docs, one module per family of result
files; ``scripts/render_figures.py`` is the engine that finds the blocks and rewrites them.

Each module exposes ``FIGURES``: marker id -> :class:`base.Figure` (the result files under
``docs/results/`` it reads, and the function that turns them into the block's markdown).
"""

from __future__ import annotations

from . import bench, completion, evaluation, filter_checks, nodes
from .base import Figure

FIGURES: dict[str, Figure] = {}
for _module in (bench, completion, evaluation, filter_checks, nodes):
    _clash = FIGURES.keys() & _module.FIGURES.keys()
    if _clash:
        raise ValueError(f"figure ids defined twice: {sorted(_clash)}")
    FIGURES.update(_module.FIGURES)
