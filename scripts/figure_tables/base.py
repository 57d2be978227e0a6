"""What every figure renderer shares: the :class:`Figure` record and the markdown formatting."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class Figure:
    """A figure block: the result files it is rendered from (names under ``docs/results/``) and the
    function that turns them (name -> parsed JSON) into the block's markdown lines."""

    sources: tuple[str, ...]
    render: Callable[[dict[str, dict[str, Any]]], list[str]]


def one(source: str, render: Callable[[dict[str, Any]], list[str]]) -> Figure:
    """A figure rendered from a single result file."""
    return Figure((source,), lambda results: render(results[source]))



def table(header: list[str], rows: list[list[Any]]) -> list[str]:
    """A markdown table."""
    lines = ["| " + " | ".join(header) + " |", "| " + " | ".join("---" for _ in header) + " |"]
    return lines + ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]


def ms(value: float) -> str:
    return f"{value:.2f} ms"


def ratio(value: float) -> str:
    return f"{value:.2f}x"


def met(flag: bool | None) -> str:
    return {True: "met", False: "**not met**", None: "-"}[flag]



def pct(value: float, digits: int = 1) -> str:
    """A share (0-1) as a percentage."""
    return f"{100 * value:.{digits}f} %"
