"""Recall against returns (pcc_ros.workflows.detector_recall) on hand-built frames."""

from __future__ import annotations

import json

import numpy as np

from pcc_ros.metrics.detection import FrameBoxes
from pcc_ros.types import Boxes
from pcc_ros.workflows.detection_eval import LabelledFrame
from pcc_ros.workflows.detector_recall import car_rows, main, recall_table


def _cars(xs: list[float], label: str = "Car") -> Boxes:
    k = len(xs)
    return Boxes(np.c_[xs, np.zeros(k), np.zeros(k)], np.tile([4.0, 1.8, 1.5], (k, 1)), np.zeros(k), [label] * k,
                 np.ones(k))


def _returns(x: float, n: int, z: float = 0.2) -> np.ndarray:
    """``n`` returns on the car at ``x`` at height ``z`` over its centre (the box spans -0.75..0.75)."""
    return np.c_[np.linspace(x - 1.5, x + 1.5, n), np.zeros(n), np.full(n, z), np.zeros(n)]


def _frame(kinds=None) -> LabelledFrame:
    # A near car with 30 body returns, detected; a far car with 3 body returns and 10 ground returns
    # (under the body margin), not detected unless a detection is counted; a Van with 8 returns, detected.
    points = np.r_[_returns(10.0, 30), _returns(50.0, 3), _returns(50.0, 10, z=-0.7), _returns(30.0, 8)]
    gt = Boxes.concatenate([_cars([10.0, 50.0]), _cars([30.0], "Van")])
    dt = Boxes.concatenate([_cars([10.1, 50.2, 30.0])])
    return LabelledFrame("f", points, FrameBoxes(gt), FrameBoxes(dt), np.zeros((0, 4)), kinds=kinds)


def test_returns_leave_ground_out_and_recall_bins_count_each_car():
    rows = car_rows([_frame()])
    assert rows["returns"].tolist() == [30, 3, 8]
    assert rows["detected"].tolist() == [True, True, True]
    table = recall_table(rows)
    assert table["recall_by_returns"]["1-4"] == {"labelled": 1, "detected": 1, "recall": 1.0}
    assert table["recall_by_returns"]["20-49"]["labelled"] == 1
    assert table["recall_by_range"]["40+"]["labelled"] == 1
    sparse = table["true_detections_by_range"]["all"]
    assert sparse["true_detections"] == 3 and sparse["under_5"] == 1 / 3 and sparse["under_10"] == 2 / 3


def test_synthcars_kinds_count_only_true_detections():
    # The box on the far car is a misplaced one: no detection of that car.
    rows = car_rows([_frame(np.array(["true", "misplaced", "true"], dtype=object))], ("Car",))
    assert rows["returns"].tolist() == [30, 3]  # the Van is not among --gt-classes Car
    assert rows["detected"].tolist() == [True, False]
    assert recall_table(rows)["recall_by_returns"]["1-4"]["recall"] == 0.0


def test_the_command_on_the_real_sequence(shared_data, tmp_path):
    out, root = tmp_path / "r.json", shared_data / "kitti_tracking"
    assert main(["--kitti", str(root), "--detections", str(root / "detections" / "pointrcnn"), "--json", str(out),
                 "--plot", str(tmp_path / "r.png")]) == 0
    table = json.loads(out.read_text())[str(root)]
    assert table["labelled"] == 35 and table["detected"] == 32
    assert (tmp_path / "r.png").stat().st_size > 0
