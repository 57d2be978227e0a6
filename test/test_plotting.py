"""Box labels of the BEV PNGs (`pcc demo`, SynthCars previews): every label drawn, readable, apart."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import pytest

from pcc_ros.geometry.boxes import box_corners
from pcc_ros.plotting import label_boxes
from pcc_ros.types import Boxes


def _boxes(centers, yaws) -> Boxes:
    n = len(centers)
    centers = np.c_[np.asarray(centers, dtype=float), np.zeros(n)]
    return Boxes(center=centers, size=np.tile([4.2, 1.8, 1.5], (n, 1)), yaw=np.asarray(yaws, dtype=float))


def _extents(artists, renderer) -> np.ndarray:
    return np.array([a.get_window_extent(renderer).extents for a in artists])


def _overlaps(a, b) -> bool:
    return min(a[2], b[2]) > max(a[0], b[0]) and min(a[3], b[3]) > max(a[1], b[1])


@pytest.mark.parametrize("scene", ["parked_row", "overlapping_pair", "at_the_edge"])
def test_every_label_is_drawn_outside_every_box_and_apart_from_the_others(scene):
    if scene == "parked_row":  # a row of parked cars nose to tail, and a second row 2.5 m beside it
        centers = [(x, y) for y in (8.0, 10.5) for x in np.arange(10.0, 40.0, 4.8)]
    elif scene == "overlapping_pair":  # two detections of one car, plus a neighbour (the demo's KITTI frame)
        centers = [(38.9, 8.8), (39.3, 9.1), (43.0, 11.0), (15.5, 5.5)]
    else:  # boxes cut by the axes' edge
        centers = [(48.6, 14.7), (43.0, 17.0), (-49.0, -38.5)]
    yaws = np.linspace(0.0, 0.6, len(centers))
    boxes = _boxes(centers, yaws)
    fig, ax = plt.subplots(figsize=(11, 9), dpi=110)
    corners = box_corners(boxes)[:, [0, 1, 2, 3, 0], :2]
    for c in corners:
        ax.plot(c[:, 0], c[:, 1])
    ax.set_aspect("equal")
    ax.set_xlim(-50, 50)
    ax.set_ylim(-40, 40)
    texts = [f"{s:.2f}" for s in np.linspace(0, 1, len(centers))]
    texts[-1] = None  # a box the filter did not judge gets no label
    artists = label_boxes(ax, corners, texts, ["tab:green"] * len(centers))
    renderer = fig.canvas.get_renderer()
    assert [a.get_text() for a in artists] == [t for t in texts if t is not None]
    labels = _extents(artists, renderer)
    shown = np.stack([ax.transData.transform(c) for c in corners])
    box_extents = np.c_[shown.min(axis=1), shown.max(axis=1)]
    frame = ax.get_window_extent(renderer).extents
    for i, label in enumerate(labels):
        assert frame[0] <= label[0] and label[2] <= frame[2] and frame[1] <= label[1] and label[3] <= frame[3]
        for j, other in enumerate(labels):
            assert j == i or not _overlaps(label, other), (artists[i].get_text(), artists[j].get_text())
        if scene != "overlapping_pair":  # two boxes on one car leave no free side for each other's label
            for k, box in enumerate(box_extents):
                assert not _overlaps(label, box), (artists[i].get_text(), k)
    # Each label is near its own box (beside it, not pushed across the plot).
    centres = np.c_[(labels[:, 0] + labels[:, 2]) / 2, (labels[:, 1] + labels[:, 3]) / 2]
    own = box_extents[[i for i, t in enumerate(texts) if t is not None]]
    reach = np.hypot(own[:, 2] - own[:, 0], own[:, 3] - own[:, 1]) + 60
    assert (np.hypot(centres[:, 0] - (own[:, 0] + own[:, 2]) / 2, centres[:, 1] - (own[:, 1] + own[:, 3]) / 2)
            < reach).all()
    plt.close(fig)
