"""Builders and assertions shared by the standing fuzz corpus (``test_fuzz_*.py``).

Small synthetic inputs (a few thousand points, one car per frame) so hundreds of damaged
variants run in seconds; every damaged input must end in a *named* error (``ERROR pcc:``
with the file, never ``internal error``, never a traceback) or a counted skip, and a failed
command must leave no output behind. The checks themselves are conftest's
(:func:`conftest.assert_named_failure`), the one helper every error-path test uses.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
from hypothesis import strategies as st

from pcc_ros.types import Boxes, Sample

CAR = dict(center=(10.0, 2.0, 0.8), size=(4.2, 1.8, 1.5), yaw=0.3)

#: Bytes a JSON reader must refuse by name or read whole: random bytes, or random JSON documents.
RANDOM_JSON_BYTES = st.one_of(
    st.binary(max_size=300),
    st.recursive(st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=5),
                 lambda c: st.lists(c, max_size=3) | st.dictionaries(st.text(max_size=8), c, max_size=4),
                 max_leaves=30).map(lambda v: json.dumps(v).encode()),
)


def car_points(rng: np.random.Generator, n: int = 400) -> np.ndarray:
    """Points on the surface of the car box ``CAR`` (scan frame)."""
    local = rng.uniform(-0.5, 0.5, size=(n, 3)) * np.array(CAR["size"])
    face = rng.integers(0, 3, n)
    local[np.arange(n), face] = np.sign(local[np.arange(n), face]) * np.array(CAR["size"])[face] / 2
    c, s = np.cos(CAR["yaw"]), np.sin(CAR["yaw"])
    world = local @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T + np.array(CAR["center"])
    return world


def small_frames(n: int = 3, seed: int = 0, points: int = 1500) -> list[Sample]:
    """``n`` frames 0.1 s apart: ground clutter + one car, detections and ground truth of it."""
    rng = np.random.default_rng(seed)
    frames = []
    for i in range(n):
        clutter = np.c_[rng.uniform(-30, 30, (points, 2)), rng.uniform(-1.0, 0.0, points)]
        xyz = np.concatenate([clutter, car_points(rng)]).astype(np.float32)
        pts = np.c_[xyz, rng.uniform(0, 1, len(xyz)).astype(np.float32)]
        box = Boxes(np.array([CAR["center"]]), np.array([CAR["size"]]), np.array([CAR["yaw"]]),
                    np.array(["Car"], dtype=object), np.array([0.9]), np.array(["7"], dtype=object))
        frames.append(Sample(stamp_ns=1_700_000_000_000_000_000 + i * 100_000_000, frame_id="velodyne",
                            points=pts, fields=("x", "y", "z", "intensity"), detections=box,
                            ground_truth=box, sequence="0000", index=i))
    return frames


def copy_tree(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


def flip(path: Path, offset: int, mask: int = 0x10) -> None:
    data = bytearray(path.read_bytes())
    data[offset] ^= mask
    path.write_bytes(bytes(data))
