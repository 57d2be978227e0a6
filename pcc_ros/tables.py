"""Aligned text tables for the terminal (benchmarks, ``pcc eval``, ``pcc replay``, the demo)."""

from __future__ import annotations


def metric_cell(value: object) -> str:
    """A metric in a table cell: 4 significant digits (squared metres of good completions are
    ~1e-4), '-' for an empty band (``None``)."""
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)


def print_table(title: str, rows: list[dict], columns: list[str] | None = None) -> None:
    """Print ``rows`` (dicts) as an aligned text table."""
    if not rows:
        print(f"{title}: no rows")
        return
    columns = columns or list(rows[0])

    def cell(v: object) -> str:
        if isinstance(v, float):
            return f"{v:.3f}" if abs(v) < 1000 else f"{v:.0f}"
        return str(v)

    body = [[cell(r.get(c, "")) for c in columns] for r in rows]
    widths = [max(len(c), *(len(b[i]) for b in body)) for i, c in enumerate(columns)]
    print(f"\n{title}")
    print("  ".join(c.ljust(w) for c, w in zip(columns, widths)))
    print("  ".join("-" * w for w in widths))
    for b in body:
        print("  ".join(v.ljust(w) for v, w in zip(b, widths)))
