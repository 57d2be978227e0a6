"""Bird's-eye-view PNG of one simulated frame: points, ground-truth boxes, true / false detections."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from pcc_ros.geometry.boxes import box_corners
from pcc_ros.plotting import label_boxes
from pcc_ros.types import Boxes


def _outline(ax, boxes: Boxes, color: str, lw: float, ls: str = "-", label: str | None = None) -> None:
    corners = box_corners(boxes)[:, 4:, :2]  # top face, in order
    for i, c in enumerate(corners):  # one polyline per box
        loop = np.r_[c, c[:1]]
        ax.plot(loop[:, 0], loop[:, 1], color=color, lw=lw, ls=ls, label=label if i == 0 else None)
        # heading tick: centre -> front
        front = boxes.center[i, :2] + 0.5 * boxes.size[i, 0] * np.array([np.cos(boxes.yaw[i]), np.sin(boxes.yaw[i])])
        ax.plot([boxes.center[i, 0], front[0]], [boxes.center[i, 1], front[1]], color=color, lw=lw)


def render_bev(
    points: np.ndarray,
    gt: Boxes,
    detections: Boxes,
    detection_true: np.ndarray,
    path: str | Path,
    title: str = "",
    extent: float = 50.0,
) -> Path:
    """Write the BEV PNG: points by height, GT green, true detections blue, false red (with scores)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(11, 11), dpi=110)  # the saved dpi: labels are placed in display space
    sel = (np.abs(points[:, 0]) < extent) & (np.abs(points[:, 1]) < extent)
    p = points[sel]
    ax.scatter(p[:, 0], p[:, 1], s=0.15, c=np.clip(p[:, 2], -1.8, 1.0), cmap="Greys", vmin=-2.5, vmax=1.0,
               rasterized=True)
    cars = gt[np.isin(gt.label, ["Car", "Van"])]
    peds = gt[gt.label == "Pedestrian"]
    _outline(ax, cars, "tab:green", 1.6, label=f"ground truth Car/Van ({len(cars)})")
    _outline(ax, peds, "tab:olive", 1.0, label=f"ground truth Pedestrian ({len(peds)})")
    true, false = detections[detection_true], detections[~detection_true]
    _outline(ax, true, "tab:blue", 1.0, "--", label=f"true detections ({len(true)})")
    _outline(ax, false, "tab:red", 1.2, "--", label=f"false detections ({len(false)})")
    ax.plot([0], [0], marker=">", color="k", ms=10)
    ax.set_xlim(-extent, extent)
    ax.set_ylim(-extent, extent)
    ax.set_aspect("equal")
    ax.set_xlabel("x forward (m)")
    ax.set_ylabel("y left (m)")
    ax.set_title(title)
    ax.legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    inside = (np.abs(detections.center[:, 0]) < extent) & (np.abs(detections.center[:, 1]) < extent)
    shown = detections[inside]
    label_boxes(ax, box_corners(shown)[:, 4:, :2], [f"{s:.2f}" for s in shown.score],
                np.where(detection_true[inside], "tab:blue", "tab:red"))  # scores beside the boxes, none hidden
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
