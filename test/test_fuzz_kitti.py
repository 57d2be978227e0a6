"""Fuzz corpus, KITTI: damaged calibration, label and detector files and missing scans.

Each case through ``pcc convert``: a named error with ``file[:line]`` and no bag left
behind, never a traceback and never silently fewer frames or boxes.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from conftest import assert_named_failure, run_cli
from hypothesis import given, settings
from hypothesis import strategies as st

from pcc_ros.data.kitti import KittiObject
from pcc_ros.data.kitti_format import Calibration, parse_label_lines
from pcc_ros.errors import DataError

FRAMES = 3


def tracking_copy(shared_data: Path, dst: Path) -> Path:
    """Sequence 0000, frames 0-2, with its calibration, labels (those frames) and detections."""
    src = shared_data / "kitti_tracking"
    (dst / "training/velodyne/0000").mkdir(parents=True)
    (dst / "training/label_02").mkdir()
    (dst / "det/0000").mkdir(parents=True)
    for i in range(FRAMES):
        shutil.copy(src / f"training/velodyne/0000/{i:06d}.bin", dst / "training/velodyne/0000")
        shutil.copy(src / f"detections/pointrcnn/0000/{i:06d}.txt", dst / "det/0000")
    shutil.copytree(src / "training/calib", dst / "training/calib")
    lines = (src / "training/label_02/0000.txt").read_text().splitlines()
    (dst / "training/label_02/0000.txt").write_text("".join(f"{x}\n" for x in lines if int(x.split()[0]) < FRAMES))
    return dst


def _edit(path: Path, fn) -> None:
    lines = path.read_text().splitlines()
    path.write_text("".join(f"{x}\n" for x in fn(lines)))


def _calib_key(lines, key, fn):
    return [fn(x) if x.split()[0].rstrip(":") in key else x for x in lines]


def _singular(x):
    return x.split()[0] + " 1 0 0 1 0 0 0 0 0"


def _nan_first(x):
    parts = x.split()
    return " ".join([parts[0], "nan", *parts[2:]])


def _negative_size(lines):
    out = []
    for x in lines:
        parts = x.split()
        if parts[2] != "DontCare":
            parts[10] = str(-abs(float(parts[10])))
        out.append(" ".join(parts))
    return out


CASES = {
    # name: (edit(root), the text the error must contain)
    "singular R0_rect": (lambda r: _edit(r / "training/calib/0000.txt",
                                         lambda ls: _calib_key(ls, ("R0_rect", "R_rect"), _singular)),
                         ["calib/0000.txt", "R0_rect is not a rotation"]),
    "NaN Tr_velo_to_cam": (lambda r: _edit(r / "training/calib/0000.txt",
                                           lambda ls: _calib_key(ls, ("Tr_velo_to_cam", "Tr_velo_cam"), _nan_first)),
                           ["calib/0000.txt:", "non-finite value in Tr_velo"]),
    "binary label file": (lambda r: (r / "training/label_02/0000.txt").write_bytes(bytes(range(256)) * 8),
                          ["label_02/0000.txt:", "not a KITTI text file"]),
    "NaN score": (lambda r: _edit(r / "det/0000/000001.txt",
                                  lambda ls: [ls[0].rsplit(" ", 1)[0] + " nan", *ls[1:]]),
                  ["det/0000/000001.txt:1", "non-finite score"]),
    "negative sizes": (lambda r: _edit(r / "training/label_02/0000.txt", _negative_size),
                       ["label_02/0000.txt:", "must be > 0"]),
    "missing scan": (lambda r: (r / "training/velodyne/0000/000001.bin").unlink(),
                     ["velodyne/0000/000001.bin", "missing scan"]),
    "truncated scan": (lambda r: (r / "training/velodyne/0000/000002.bin").write_bytes(b"\0" * 10),
                       ["000002.bin", "not a multiple"]),
}


@pytest.mark.parametrize("case", list(CASES))
def test_damaged_kitti_is_a_named_error_and_writes_nothing(shared_data, tmp_path, caplog, case):
    root = tracking_copy(shared_data, tmp_path / "kitti")
    out = tmp_path / "bag"
    args = ["convert", "kitti-tracking", root, "--sequence", "0000", "--detections", root / "det", "--out", out]
    rc, text = run_cli(args, caplog)
    assert rc == 0, text  # the intact copy converts
    shutil.rmtree(out)
    edit, names = CASES[case]
    edit(root)
    rc, text = run_cli(args, caplog)
    assert_named_failure(rc, text, *names, output=out)


def test_kitti_object_scan_gap_is_named(shared_data, tmp_path):
    src = shared_data / "kitti_object/training"
    root = tmp_path / "obj"
    shutil.copytree(src, root)
    scans = sorted((root / "velodyne").glob("*.bin"))
    assert len(scans) >= 3
    scans[1].unlink()
    with pytest.raises(DataError, match=f"{scans[1].name}: missing scan"):
        list(KittiObject(root).frames())


# ----------------------------------------------------------------------------- hypothesis

_TOKENS = st.one_of(
    st.sampled_from(["Car", "Van", "DontCare", "Pedestrian", "nan", "inf", "-inf", "-1", "0", "1e308", "-0", "x"]),
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.integers(-10**6, 10**6).map(str),
)
_LINES = st.lists(st.lists(_TOKENS, min_size=0, max_size=20).map(" ".join), max_size=6)


@settings(max_examples=300, deadline=None)
@given(lines=_LINES, tracking=st.booleans())
def test_label_lines_parse_or_raise_a_named_error(lines, tracking):
    try:
        rows = parse_label_lines(lines, tracking=tracking, source="labels.txt")
    except DataError as exc:
        assert str(exc).startswith("labels.txt:")
        return
    assert len(rows) == sum(1 for x in lines if x.split())
    assert np.isfinite(rows.hwl).all() and np.isfinite(rows.score).all() and np.isfinite(rows.location).all()
    real = rows.type != "DontCare"
    assert (rows.hwl[real] > 0).all()


@settings(max_examples=150, deadline=None)
@given(data=st.one_of(st.binary(max_size=600), _LINES.map("\n".join).map(str.encode)))
def test_calibration_files_parse_or_raise_a_named_error(tmp_path_factory, data):
    path = tmp_path_factory.mktemp("calib") / "0000.txt"
    path.write_bytes(data)
    try:
        calib = Calibration.read(path)
    except DataError as exc:
        assert str(path) in str(exc)
        return
    assert np.isfinite(calib.rect_to_velo).all()  # never a singular or non-finite transform
