"""Matplotlib helpers shared by the PNGs the tools write (``pcc demo``, SynthCars previews, ``pcc eval``).

:func:`label_boxes` puts one text label beside each box of a bird's-eye view so that no label
sits inside a box (on top of that car's points, where a label in the box's colour vanishes),
over another box, over another label or outside the axes: a row of parked cars or two
overlapping detections still get every label, readable.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

#: Where a label may go relative to its box's bird's-eye-view extent, tried in this order:
#: (x anchor 0..1 over the box, y anchor, horizontal alignment, vertical alignment, x / y
#: direction of the offset). Above first, then below, right, left, then the four corners.
_SPOTS = (
    (0.5, 1.0, "center", "bottom", 0, 1),
    (0.5, 0.0, "center", "top", 0, -1),
    (1.0, 0.5, "left", "center", 1, 0),
    (0.0, 0.5, "right", "center", -1, 0),
    (1.0, 1.0, "left", "bottom", 1, 1),
    (0.0, 1.0, "right", "bottom", -1, 1),
    (1.0, 0.0, "left", "top", 1, -1),
    (0.0, 0.0, "right", "top", -1, -1),
)


def _overlap(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Overlap areas of one display rectangle ``a`` (x0, y0, x1, y1) with rectangles ``b`` (M, 4)."""
    if len(b) == 0:
        return np.zeros(0)
    w = np.minimum(a[2], b[:, 2]) - np.maximum(a[0], b[:, 0])
    h = np.minimum(a[3], b[:, 3]) - np.maximum(a[1], b[:, 1])
    return np.clip(w, 0, None) * np.clip(h, 0, None)


def label_boxes(ax, corners: np.ndarray, texts: Sequence[str | None], colors: Sequence, fontsize: float = 7,
                gap_px: float = 3.0) -> list:
    """Draw ``texts[i]`` beside box ``i`` (``corners``: (N, K, 2) bird's-eye-view corners in data
    units; ``None`` draws nothing) and return the text artists.

    Each label takes the first spot around its box (above, below, right, left, the corners;
    then the same twice as far out) that overlaps no box, no label placed before it, not the
    legend and stays inside the axes; where every spot collides, the one with the least overlap. Call it after
    the axes' limits, aspect and legend are set (it measures in display space)."""
    fig = ax.figure
    ax.apply_aspect()
    renderer = fig.canvas.get_renderer()
    to_display = ax.transData.transform
    corners = np.asarray(corners, dtype=float).reshape(len(texts), -1, 2) if len(texts) else np.zeros((0, 4, 2))
    shown = np.stack([to_display(c) for c in corners]) if len(corners) else np.zeros((0, 4, 2))
    boxes = np.concatenate([shown.min(axis=1), shown.max(axis=1)], axis=1) if len(shown) else np.zeros((0, 4))
    frame = ax.get_window_extent(renderer).extents
    legend = ax.get_legend()  # drawn before: its corner is taken as well
    placed: list[np.ndarray] = [np.array(legend.get_window_extent(renderer).extents)] if legend else []
    artists = []
    pad = 2.0  # pixels of the label's background beyond its glyphs
    for i, text in enumerate(texts):
        if text is None:
            continue
        x0, y0, x1, y1 = boxes[i]
        artist = ax.text(0, 0, text, fontsize=fontsize, color=colors[i], zorder=6, clip_on=True,
                         bbox={"boxstyle": f"square,pad={pad / fontsize:.3f}", "fc": "white", "ec": "none",
                               "alpha": 0.8})
        best, best_cost = None, np.inf
        for reach in (1.0, 2.5):
            for fx, fy, ha, va, dx, dy in _SPOTS:
                anchor = np.array([x0 + fx * (x1 - x0) + dx * gap_px * reach,
                                   y0 + fy * (y1 - y0) + dy * gap_px * reach])
                artist.set_position(ax.transData.inverted().transform(anchor))
                artist.set_ha(ha)
                artist.set_va(va)
                extent = np.asarray(artist.get_window_extent(renderer).extents) + np.array([-pad, -pad, pad, pad])
                outside = max(frame[0] - extent[0], 0) + max(extent[2] - frame[2], 0) \
                    + max(frame[1] - extent[1], 0) + max(extent[3] - frame[3], 0)
                cost = (_overlap(extent, boxes).sum() + _overlap(extent, np.array(placed).reshape(-1, 4)).sum()
                        + 1e3 * outside)
                if cost < best_cost:
                    best, best_cost = (artist.get_position(), ha, va, extent), cost
                if cost == 0:
                    break
            if best_cost == 0:
                break
        position, ha, va, extent = best
        artist.set_position(position)
        artist.set_ha(ha)
        artist.set_va(va)
        placed.append(extent)
        artists.append(artist)
    return artists


def plot_examples(
    path: Path,
    instances: Sequence[Any],
    completions: dict[str, Any],
    reference: str,
    picks: Sequence[int],
    max_draw: int = 2048,
) -> None:
    """A PNG grid: one row per example instance, columns input / each backend / reference.

    ``instances``: :class:`pcc_ros.workflows.evaluate.EvalInstance` (``partial``, ``reference``, ``key``,
    ``distance``, ``num_points``). ``picks`` are instance indices (``evaluate.example_indices``
    spreads them over the distance range so near and far cars both appear);
    ``completions[name][i]`` is backend ``name``'s completion of instance ``i`` (a list or a
    dict). Clouds are drawn in 3D in the canonical frame from the same viewpoint.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    count = len(picks)
    if count == 0:
        raise ValueError("plot_examples: no instances to draw")
    names = [n for n in completions if n != "input"]  # the partial column already shows it
    columns = ["partial input", *names, "ground truth" if reference == "ground_truth" else "aggregated reference"]
    fig = plt.figure(figsize=(2.6 * len(columns), 2.4 * count))
    rng = np.random.default_rng(0)
    for row, idx in enumerate(picks):
        inst = instances[idx]
        clouds = [inst.partial, *(completions[n][idx] for n in names), inst.reference]
        for col, (title, cloud) in enumerate(zip(columns, clouds)):
            ax = fig.add_subplot(count, len(columns), row * len(columns) + col + 1, projection="3d")
            if len(cloud) > max_draw:
                cloud = cloud[rng.choice(len(cloud), max_draw, replace=False)]
            colour = "tab:red" if col == 0 else ("tab:green" if col == len(columns) - 1 else "tab:blue")
            ax.scatter(cloud[:, 0], cloud[:, 1], cloud[:, 2], s=1.0, c=colour, depthshade=False, linewidths=0)
            ax.set_xlim(-0.6, 0.6)
            ax.set_ylim(-0.6, 0.6)
            ax.set_zlim(-0.6, 0.6)
            ax.set_box_aspect((1, 1, 1))
            ax.view_init(elev=40, azim=-50)
            ax.set_xticks([])
            ax.set_yticks([])
            ax.set_zticks([])
            if row == 0:
                ax.set_title(title, fontsize=9)
            if col == 0:
                ax.text2D(
                    0.0, 0.0, f"{inst.key}\n{inst.distance:.0f} m, {inst.num_points} pts", transform=ax.transAxes,
                    fontsize=7,
                )
    fig.suptitle("canonical frame (x forward, y left, z up; box length = 1)", fontsize=9)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def operating_curves(ax, curves: dict[str, dict[str, np.ndarray]], configured: tuple[float, float], max_lost: float,
                     true_label: str, false_label: str, xlim: tuple[float, float]) -> None:
    """A filter's operating-curve panel: per method, false removed against true lost (shares,
    drawn in %) as steps; the configured threshold's point as a star; the loss budget as a
    dotted line. The detection checks (``pcc eval detections``, its nuScenes check) draw it alike."""
    for name, curve in curves.items():
        ax.plot(100 * curve["true_lost"], 100 * curve["false_removed"], drawstyle="steps-post", label=name)
    ax.plot([100 * configured[0]], [100 * configured[1]], "k*", ms=12, label="filter, configured")
    ax.axvline(100 * max_lost, color="grey", ls=":", lw=1)
    ax.set_xlabel(f"{true_label} lost (%)")
    ax.set_ylabel(f"{false_label} removed (%)")
    ax.set_xlim(*xlim)
    ax.set_title("operating curves")
    ax.legend(loc="lower right", fontsize=8)
