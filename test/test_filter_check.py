"""The cross-sensor check on the real nuScenes frame (``pcc eval detections --nuscenes``)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pcc_ros.cli.main import main
from pcc_ros.geometry.boxes import iou_bev
from pcc_ros.workflows.filter_check import CAR_SIZE, constructed_boxes


@pytest.fixture()
def nuscenes_root(shared_data):
    root = shared_data / "nuscenes_mini"
    if not (root / "v1.0-mini").is_dir():
        pytest.skip("no nuScenes sample in ../shared/data")
    return root


def test_constructed_boxes_on_the_real_frame(nuscenes_root):
    from pcc_ros.data.nuscenes import NuScenes

    sample = next(NuScenes(nuscenes_root).frames())
    boxes, group, is_true = constructed_boxes(sample.points, sample.ground_truth, sample.extras["category"], 0.7, 20,
                                              seed=3, nms_iou=1.0)  # every box
    assert is_true.sum() == 8  # the annotated cars
    assert (group == "human.pedestrian.adult").sum() == 30 and (group == "movable_object.barrier").sum() == 22
    ground = group == "free ground"
    assert ground.sum() == 20 and np.all(boxes.score == 0.7)
    np.testing.assert_allclose(boxes.size[~is_true], np.tile(CAR_SIZE, ((~is_true).sum(), 1)))
    assert iou_bev(boxes[ground], sample.ground_truth).max() <= 0.0  # free ground overlaps no annotation
    again = constructed_boxes(sample.points, sample.ground_truth, sample.extras["category"], 0.7, 20, seed=3,
                              nms_iou=1.0)[0]
    assert again.equals(boxes)  # seeded
    # the NMS rule: no false box overlaps a kept box above the IoU, every car stays, the rest dropped
    suppressed: dict[str, int] = {}
    nms, nms_group, nms_true = constructed_boxes(sample.points, sample.ground_truth, sample.extras["category"], 0.7,
                                                 20, seed=3, nms_iou=0.2, suppressed=suppressed)
    assert nms_true.sum() == 8 and len(nms) == len(boxes) - sum(suppressed.values()) and suppressed
    iou = iou_bev(nms, nms)
    np.fill_diagonal(iou, 0.0)
    assert iou[~nms_true].max() <= 0.2
    assert suppressed.get("human.pedestrian.adult", 0) == 30 - (nms_group == "human.pedestrian.adult").sum()


def test_nuscenes_check_writes_curve_and_png(nuscenes_root, tmp_path):
    out_json, out_png = tmp_path / "nus.json", tmp_path / "nus.png"
    assert main(["eval-detections", "--nuscenes", str(nuscenes_root), "--ground-boxes", "10", "--json", str(out_json),
                 "--plot", str(out_png)]) == 0
    result = json.loads(out_json.read_text())
    dropped = sum(result["suppressed_by_nms"].values())  # the NMS rule's (a detector emits none of them)
    assert result["true"] == 8 and result["false"] == 57 + 10 - dropped and dropped > 0 and result["nms_iou"] == 0.2
    curve = result["methods"]["filter"]["curve"]
    assert curve["false_removed"][0] == 0 and curve["false_removed"][-1] > 0.5 and curve["true_lost"][-1] > 0
    assert "points-in-box" in result["methods"] and len(result["well_seen_cars"]) == 1
    assert set(result["by_score"]) == {"0.5", "0.7", "0.9"}
    assert out_png.stat().st_size > 20_000 and out_png.read_bytes()[:4] == b"\x89PNG"
    # the shipped rule's overlap term reads the check's boxes overlapping below the NMS IoU: the
    # figure without it is reported beside, and it can only remove fewer
    conf = result["configured"]
    assert conf["non_vehicle_overlapping_another"] > 0
    assert conf["non_vehicle_removed_without_overlap"] <= conf["non_vehicle_removed"]


def test_nuscenes_check_without_the_ring_field_finds_the_same_sensor(nuscenes_root, monkeypatch):
    """A driver or a conversion that drops the ring field: the beam model is estimated from the
    returns' elevations alone, still matches the HDL-32E preset, and the shipped rule removes the
    same share of the non-vehicle boxes and keeps the car with 46 returns (docs/filter.md, "Which
    preset it is": at a 0.5 deg ring-less tolerance it matched nothing and removed 69.8 %)."""
    from pcc_ros.cli.eval_detections import build_pipeline
    from pcc_ros.data.nuscenes import NuScenes
    from pcc_ros.workflows.filter_check import nuscenes_check

    frames = NuScenes.frames

    def without_ring(self, scene=None):
        for sample in frames(self, scene):
            column = list(sample.fields).index("ring")
            sample.fields = tuple(f for f in sample.fields if f != "ring")
            sample.points = np.delete(np.asarray(sample.points), column, axis=1)
            yield sample

    monkeypatch.setattr(NuScenes, "frames", without_ring)
    result = nuscenes_check(nuscenes_root, build_pipeline(None, {"backend": "input"}))
    assert result["threshold_in_force"]["preset"] == "hdl32"
    assert result["configured"]["non_vehicle_removed"] >= 0.75
    assert result["well_seen_cars_kept"] and result["configured"]["true_lost_count"] <= 1
