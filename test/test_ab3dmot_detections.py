"""AB3DMOT's published PointRCNN detections (one comma-separated file per KITTI tracking sequence)
read as the same boxes as the per-frame KITTI-format files they were rewritten into."""

from __future__ import annotations

import numpy as np
import pytest

from pcc_ros.data.kitti import KittiTracking
from pcc_ros.errors import DataError

TYPE_IDS = {"Pedestrian": 1, "Car": 2, "Cyclist": 3}


def _ab3dmot_file(per_frame_dir, out) -> int:
    """Write AB3DMOT's layout (frame, type id, 2D box, score, h w l x y z rot_y, alpha) from per-frame
    KITTI lines (type, truncated, occluded, alpha, 2D box, h w l x y z rot_y, score); frames left empty
    stay absent, as in AB3DMOT's files."""
    lines = []
    for path in sorted(per_frame_dir.glob("*.txt")):
        for row in path.read_text().split("\n"):
            p = row.split()
            if p:
                lines.append(",".join([str(int(path.stem)), str(TYPE_IDS[p[0]]), *p[4:8], p[15], *p[8:15], p[3]]))
    out.write_text("\n".join(lines) + "\n")
    return len(lines)


def test_per_sequence_file_equals_per_frame_files(shared_data, tmp_path):
    root = shared_data / "kitti_tracking"
    per_frame = root / "detections" / "pointrcnn"
    rows = _ab3dmot_file(per_frame / "0000", tmp_path / "0000.txt")
    reader = KittiTracking(root)
    expected = list(reader.frames("0000", per_frame, stop=6))
    got = list(reader.frames("0000", tmp_path, stop=6))
    assert rows > 0 and sum(len(f.detections) for f in got) > 0
    for a, b in zip(expected, got):
        np.testing.assert_allclose(b.detections.center, a.detections.center, atol=1e-9)
        np.testing.assert_allclose(b.detections.size, a.detections.size)
        np.testing.assert_allclose(b.detections.yaw, a.detections.yaw)
        np.testing.assert_array_equal(b.detections.score, a.detections.score)
        assert b.detections.label.tolist() == a.detections.label.tolist()


def test_a_malformed_line_names_file_and_line(shared_data, tmp_path):
    _ab3dmot_file(shared_data / "kitti_tracking" / "detections" / "pointrcnn" / "0000", tmp_path / "0000.txt")
    lines = (tmp_path / "0000.txt").read_text().splitlines()
    lines[2] = lines[2].rsplit(",", 1)[0]  # 14 columns
    (tmp_path / "0000.txt").write_text("\n".join(lines))
    with pytest.raises(DataError, match=r"0000\.txt:3: expected 15 comma-separated AB3DMOT columns"):
        list(KittiTracking(shared_data / "kitti_tracking").frames("0000", tmp_path, stop=1))


def test_eval_detections_loader_reads_the_per_sequence_file_alike(shared_data, tmp_path):
    from pcc_ros.workflows.detection_eval import load_kitti

    root = shared_data / "kitti_tracking"
    _ab3dmot_file(root / "detections" / "pointrcnn" / "0000", tmp_path / "0000.txt")
    expected = load_kitti(root, root / "detections" / "pointrcnn", frames=slice(0, 5))
    got = load_kitti(root, tmp_path, frames=slice(0, 5))
    assert sum(len(f.dt.boxes) for f in got) > 0
    for a, b in zip(expected, got):
        np.testing.assert_allclose(b.dt.boxes.center, a.dt.boxes.center, atol=1e-9)
        np.testing.assert_array_equal(b.dt.boxes.score, a.dt.boxes.score)
