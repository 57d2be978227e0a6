"""Boxes, the canonical frame and the KITTI text formats (calibration, labels)."""

from __future__ import annotations

import numpy as np
import pytest

from pcc_ros.data.kitti_format import (
    Calibration,
    camera_to_lidar_boxes,
    format_label_lines,
    lidar_to_camera_rows,
    parse_label_lines,
)
from pcc_ros.errors import DataError
from pcc_ros.geometry.canonical import (
    from_canonical,
    from_canonical_batch,
    to_canonical,
    to_canonical_batch,
)
from pcc_ros.types import Boxes


def random_boxes(rng: np.random.Generator, n: int) -> Boxes:
    return Boxes(
        center=rng.uniform(-30, 30, (n, 3)),
        size=rng.uniform(1, 5, (n, 3)),
        yaw=rng.uniform(-np.pi, np.pi, n),
        label=["Car"] * n,
        score=rng.uniform(0, 1, n),
        track_id=[str(i) for i in range(n)],
    )


def test_boxes_selection_concat_and_validation():
    rng = np.random.default_rng(0)
    boxes = random_boxes(rng, 5)
    assert len(boxes[boxes.score > 2]) == 0
    assert len(Boxes.concatenate([boxes, boxes[[1, 2]]])) == 7
    assert boxes[3].equals(boxes[[3]])
    bad = random_boxes(rng, 3)
    bad.size[1, 0] = np.nan
    bad.center[2, 0] = np.inf
    assert bad.valid_mask().tolist() == [True, False, False]
    with pytest.raises(DataError, match="box 1"):
        bad.validate()


def test_canonical_round_trip_and_convention():
    rng = np.random.default_rng(1)
    center, yaw, length = np.array([10.0, -3.0, 0.8]), 0.7, 4.2
    # The car's front (centre + length/2 along the heading) maps to x = +0.5.
    front = center + 0.5 * length * np.array([np.cos(yaw), np.sin(yaw), 0.0])
    np.testing.assert_allclose(to_canonical(front[None], center, yaw, length), [[0.5, 0, 0]], atol=1e-12)
    pts = rng.normal(size=(100, 3)) * 3 + center
    back = from_canonical(to_canonical(pts, center, yaw, length), center, yaw, length)
    np.testing.assert_allclose(back, pts, atol=1e-9)


def test_canonical_batch_matches_single():
    rng = np.random.default_rng(2)
    pts = rng.normal(size=(4, 50, 3)) * 5
    center, yaw, length = rng.normal(size=(4, 3)), rng.uniform(-3, 3, 4), rng.uniform(3, 5, 4)
    batch = to_canonical_batch(pts, center, yaw, length)
    for b in range(4):
        np.testing.assert_allclose(batch[b], to_canonical(pts[b], center[b], yaw[b], length[b]), atol=1e-12)
    np.testing.assert_allclose(from_canonical_batch(batch, center, yaw, length), pts, atol=1e-9)


def test_calibration_accepts_both_spellings(tmp_path, shared_data):
    obj = Calibration.read(shared_data / "kitti_object/training/calib/000000.txt")
    trk = Calibration.read(shared_data / "kitti_tracking/training/calib/0000.txt")
    for calib in (obj, trk):
        assert calib.R0_rect.shape == (3, 3) and calib.Tr_velo_to_cam.shape == (3, 4)
    tracking_style = tmp_path / "calib.txt"
    tracking_style.write_text(
        "P2 " + " ".join(map(str, obj.P2.ravel())) + "\n"
        "R_rect " + " ".join(map(str, obj.R0_rect.ravel())) + "\n"
        "Tr_velo_cam " + " ".join(map(str, obj.Tr_velo_to_cam.ravel())) + "\n"
    )
    again = Calibration.read(tracking_style)
    np.testing.assert_allclose(again.velo_to_rect, obj.velo_to_rect)
    written = tmp_path / "written.txt"
    obj.write(written)
    np.testing.assert_allclose(Calibration.read(written).velo_to_rect, obj.velo_to_rect)


def test_calibration_missing_key_names_file(tmp_path):
    path = tmp_path / "broken.txt"
    path.write_text("P2: " + " ".join(["1"] * 12) + "\n")
    with pytest.raises(DataError, match=r"broken.txt.*R0_rect"):
        Calibration.read(path)


def test_label_round_trip_lidar_camera(shared_data):
    calib = Calibration.read(shared_data / "kitti_object/training/calib/000000.txt")
    rng = np.random.default_rng(3)
    boxes = random_boxes(rng, 6)
    boxes.yaw = np.angle(np.exp(1j * boxes.yaw))
    lines = format_label_lines(lidar_to_camera_rows(boxes, calib, frame=4), tracking=True, with_score=True)
    rows = parse_label_lines(lines, tracking=True)
    back = camera_to_lidar_boxes(rows, calib)
    assert back.equals(boxes, atol=1e-5)
    assert rows.frame.tolist() == [4] * 6


def test_real_kitti_label_is_converted_to_lidar_frame(shared_data):
    root = shared_data / "kitti_object/training"
    calib = Calibration.read(root / "calib/000000.txt")
    rows = parse_label_lines((root / "label_2/000000.txt").read_text().splitlines(), tracking=False)
    boxes = camera_to_lidar_boxes(rows, calib)
    # A pedestrian ~8.4 m ahead of the camera: in the LiDAR frame it is ahead (x > 0) and its
    # geometric centre is above its bottom.
    assert boxes.center[0, 0] > 5
    assert boxes.center[0, 2] > -1.73 + 0.5 * rows.hwl[0, 0] - 0.3


@pytest.mark.parametrize(
    ("line", "message"),
    [
        ("Car 0 0 0 0 0 0 0 1 1 1 1 1", "columns"),
        ("Car 0 0 0 0 0 0 0 1 1 x 1 1 1 0", "non-numeric"),
        ("Car 0 0 0 0 0 0 0 1 1 nan 1 1 1 0", "non-finite"),
    ],
)
def test_malformed_label_lines_name_their_line(line, message):
    with pytest.raises(DataError, match=f"lab.txt:2: .*{message}"):
        parse_label_lines(["Car 0 0 0 0 0 0 0 1 1 1 1 1 1 0", line], tracking=False, source="lab.txt")
