"""KITTI AP_R40 against hand-computed cases."""

from __future__ import annotations

import numpy as np
import pytest

from pcc_ros.metrics.detection import FrameBoxes, ap_table, average_precision, get_thresholds
from pcc_ros.types import Boxes

TALL = np.array([[0.0, 0.0, 50.0, 100.0]])  # a 100 px high 2D box: valid in every difficulty


def car(x: float, score: float = 1.0, label: str = "Car") -> Boxes:
    return Boxes([[x, 0.0, 0.0]], [[4.0, 1.8, 1.5]], [0.0], [label], [score])


def frame(boxes: list[Boxes], occluded=None, height: float = 100.0) -> FrameBoxes:
    b = Boxes.concatenate(boxes)
    bbox = np.tile([[0.0, 0.0, 50.0, height]], (len(b), 1))
    return FrameBoxes(b, bbox, np.zeros(len(b)), np.zeros(len(b)) if occluded is None else occluded)


def test_perfect_detections_give_100():
    gts = [frame([car(10.0)]), frame([car(20.0)])]
    dts = [frame([car(10.0, 0.9)]), frame([car(20.0, 0.8)])]
    # 2 ground truths: thresholds [0.9, 0.8], precision 1 at both samples 0 and 1, 0 after:
    # KITTI's R40 thins to one threshold per true positive, so AP = 1/40 of 100.
    assert average_precision(gts, dts).ap == pytest.approx(100.0 / 40)


def test_forty_cars_and_one_false_positive_hand_computed():
    """40 frames, one car each, detected exactly with scores 1.00, 0.99, ...; one false box
    scored between the 10th and 11th car. Thresholds are all 40 true scores; precision is 1
    for the first 10, k/(k+1) after, made monotone: 40/41 for samples 10..39, 0 for 40.
    AP = (9 * 1 + 30 * 40/41) / 40 * 100."""
    scores = 1.0 - 0.01 * np.arange(40)
    gts = [frame([car(10.0 + i)]) for i in range(40)]
    dts = [frame([car(10.0 + i, s)]) for i, s in enumerate(scores)]
    dts[0] = frame([car(10.0, scores[0]), car(-30.0, (scores[9] + scores[10]) / 2)])
    expected = (9 + 30 * 40 / 41) / 40 * 100
    result = average_precision(gts, dts, metric="3d", min_overlap=0.7)
    assert result.ap == pytest.approx(expected)
    assert average_precision(gts, dts, metric="bev", min_overlap=0.5).ap == pytest.approx(expected)


def test_iou_threshold_decides_a_true_positive():
    gts = [frame([car(10.0)]) for _ in range(40)]
    shifted = [frame([car(10.6, 0.9)]) for _ in range(40)]  # 3D/BEV IoU = 3.4/4.6 = 0.74
    assert average_precision(gts, shifted, min_overlap=0.7).ap == pytest.approx(97.5)
    far = [frame([car(11.2, 0.9)]) for _ in range(40)]  # IoU = 2.8/5.2 = 0.54
    assert average_precision(gts, far, min_overlap=0.7).ap == 0.0
    assert average_precision(gts, far, min_overlap=0.5).ap == pytest.approx(97.5)


def test_difficulty_and_neighbour_classes_are_ignored_not_false():
    # Frame 0 also holds a heavily occluded car (valid only for "hard") and a Van.
    gts = [frame([car(10.0 + i)]) for i in range(40)]
    gts[0] = frame([car(10.0), car(-20.0), car(40.0, label="Van")], occluded=np.array([0.0, 2.0, 0.0]))
    dts = [frame([car(10.0 + i, 0.9)]) for i in range(40)]
    dts[0] = frame([car(10.0, 0.9), car(-20.0, 0.95), car(40.0, 0.97)])
    table = ap_table(gts, dts, overlaps_at=(0.7,))
    assert table["3d@0.7"]["moderate"] == pytest.approx(97.5)  # occluded car, Van: ignored
    # hard: 41 valid cars, all found (41 thresholds: all 41 samples at precision 1).
    assert table["3d@0.7"]["hard"] == pytest.approx(100.0)
    # A Van counted as a Car (gt_classes): 41 moderate cars, all found.
    vehicle = average_precision(gts, dts, gt_classes=("Car", "Van"))
    assert vehicle.num_gt == 41 and vehicle.ap == pytest.approx(100.0)


def test_short_detections_are_ignored_and_no_ground_truth_is_nan():
    gts = [frame([car(10.0 + i)]) for i in range(40)]
    dts = [frame([car(10.0 + i, 0.9)]) for i in range(40)]
    dts[1] = frame([car(11.0, 0.9), car(-30.0, 0.99)], height=20.0)  # both 20 px high: ignored
    # The true car in frame 1 is absorbed by an ignored detection (neither true nor missed):
    # 39 true positives of 40 cars -> 39 thresholds, samples 1..38 at precision 1.
    assert average_precision(gts, dts).ap == pytest.approx(38 / 40 * 100)
    empty = average_precision([frame([])], [frame([car(1.0, 0.5)])])
    assert np.isnan(empty.ap) and empty.num_gt == 0


def test_thresholds_thin_to_recall_samples():
    scores = np.linspace(1.0, 0.01, 100)
    t = get_thresholds(scores.copy(), 100)
    assert len(t) == 41 and t[0] == 1.0 and t[-1] == scores[-1]
