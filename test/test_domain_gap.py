"""SynthCars realism: the sensor artefacts the real-vs-simulated comparison asked for, and the comparison."""

from __future__ import annotations

import numpy as np
import pytest

from pcc_ros.data.synthetic.lidar import REALISTIC_ARTEFACTS, Sensor, cast
from pcc_ros.data.synthetic.mesh import box, concatenate


def _block_before_wall() -> tuple:
    """A 2 x 4 x 1.5 m block 10 m ahead, a wall 14 m ahead: depth edges at the block's sides."""
    block = box(np.array([2.0, 4.0, 1.5]), np.array([10.0, 0.0, -1.0]))
    wall = box(np.array([0.5, 40.0, 6.0]), np.array([14.0, 0.0, 0.0]))
    world = concatenate([block, wall])
    return world, world.component.astype(np.int32)


def _scan(sensor: Sensor, seed: int = 0):
    world, owner = _block_before_wall()
    return cast(sensor, world, owner, np.zeros(3), 0.0, np.random.default_rng(seed))


def test_mixed_pixels_trail_behind_depth_edges_only():
    ideal = Sensor.low_res(range_noise=0.0, dropout=0.0, far_dropout=0.0)
    mixed = Sensor.low_res(range_noise=0.0, dropout=0.0, far_dropout=0.0, mixed_pixel_prob=1.0)
    a, b = _scan(ideal), _scan(mixed)
    np.testing.assert_array_equal(a.ray, b.ray)  # same rays hit; only some ranges move
    ra, rb = np.linalg.norm(a.points[:, :3], axis=1), np.linalg.norm(b.points[:, :3], axis=1)
    moved = rb - ra > 1e-3
    assert moved.any() and (rb >= ra - 1e-4).all()  # only ever pushed back, toward the background
    assert (rb - ra).max() <= 2.0 + 1e-3
    # the moved returns lie on the block's silhouette: a neighbouring column sees the wall
    on_block = a.owner == 0
    # the wall away from its own edges (its ends, its bottom edge seen by the lowest beams)
    wall_middle = ~on_block & (np.abs(a.points[:, 1]) < 15) & (a.points[:, 2] > -2.5)
    assert moved[on_block].mean() > 0.02 and not moved[wall_middle].any()
    # between the two surfaces: a mixed pixel, not a real one
    x = b.points[moved & on_block, 0]
    assert (x > 9.0).all() and (x < 14.0).all()


def test_realistic_sensor_is_deterministic_and_thicker_with_range():
    real = Sensor.realistic()
    assert {k: getattr(real, k) for k in REALISTIC_ARTEFACTS} == REALISTIC_ARTEFACTS
    assert Sensor().mixed_pixel_prob == 0 and Sensor().beam_range_bias == 0  # the default is unchanged
    low = Sensor.low_res(**REALISTIC_ARTEFACTS)
    assert low.beams == 16 and low.mixed_pixel_prob == REALISTIC_ARTEFACTS["mixed_pixel_prob"]
    np.testing.assert_array_equal(low.beam_bias, Sensor.low_res(**REALISTIC_ARTEFACTS).beam_bias)
    assert 0 < np.abs(low.beam_bias).max() < 0.1
    nominal = Sensor.low_res().elevations
    assert 0 < np.abs(low.elevations - nominal).max() < 0.3
    s1, s2 = _scan(low, seed=1), _scan(low, seed=1)
    np.testing.assert_array_equal(s1.points, s2.points)
    # weak returns (range-independent weak_dropout): fewer points than the ideal sensor
    assert len(s1.points) < len(_scan(Sensor.low_res(), seed=1).points)


@pytest.mark.slow
def test_domain_gap_statistics_and_plot(tmp_path, shared_data):
    from pcc_ros.data.domain_gap import main as gap_main
    from pcc_ros.data.instances import ExtractConfig, extract_instances
    from pcc_ros.data.sources import open_frames

    cache = extract_instances(open_frames(shared_data / "kitti_tracking"), tmp_path / "kt", ExtractConfig(),
                              source=shared_data / "kitti_tracking", progress=False)
    out = tmp_path / "gap.png"
    assert gap_main(["--real", str(cache.root), "--sim", str(cache.root), "--out", str(out)]) == 0
    import json

    report = json.loads(out.with_suffix(".json").read_text())
    real = report["real"]
    assert real["crops"] == len(cache) >= 30
    bands = [v for v in real.values() if isinstance(v, dict)]
    assert all(b["rings"] >= 2 and b["points"] >= 10 and 0 < b["thickness_mm"] < 200 for b in bands)
    assert 0 <= real["share_lowest_10pct_height"] <= 1 and out.stat().st_size > 10_000
