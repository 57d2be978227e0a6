"""The evidence filter's core on a sparse sensor: where no ring crosses the core's height band,
the rays through the cabin above it decide (``pcc_ros.pipeline.evidence.core_box``)."""

from __future__ import annotations

import numpy as np
from scan_scenes import GROUND_Z, cast

from pcc_ros.pipeline import evidence as ev
from pcc_ros.pipeline.filter import SENSOR_PRESETS, evidence
from pcc_ros.types import Boxes

VLP16, HDL64 = SENSOR_PRESETS["vlp16"], SENSOR_PRESETS["hdl64"]
# A car-sized box 35 m ahead: the VLP-16's -3 deg ring meets the road in front of it, its -1 deg
# ring crosses the box 1.1 m above its bottom, over the 0.3-0.9 m band of the core.
BOX = Boxes([[35.0, 0.0, GROUND_Z + 0.75]], [[4.2, 1.8, 1.5]], [0.0], ["Car"], [0.3])
CAR = ((32.9, -0.9, GROUND_Z + 0.3), (37.1, 0.9, GROUND_Z + 1.5))  # the car's body filling the box


def test_no_ring_of_a_sparse_sensor_crosses_the_band_where_a_dense_ones_do():
    assert ev.core_rings(BOX, VLP16)[0] == 0 and ev.core_rings(BOX, HDL64)[0] >= 3
    assert ev.core_rings(BOX, VLP16, (ev.CORE_Z[0], 1.0))[0] == 1  # the cabin's ring
    band = ev.core_box(BOX, None)
    np.testing.assert_array_equal(ev.core_box(BOX, HDL64)[1], band[1])  # dense: the band as it is
    hi = ev.core_box(BOX, VLP16)[1]
    assert hi[0, 2] == BOX.size[0, 2] / 2 and hi[0, 0] < band[1][0, 0]  # the cabin: to the top, shorter


def test_an_empty_box_between_two_rings_gets_free_space_evidence(monkeypatch):
    empty, car = evidence(cast([], VLP16), BOX, VLP16), evidence(cast([CAR], VLP16), BOX, VLP16)
    # Through the empty box the ring returns from the wall behind it; on the car it stops.
    assert empty.n_pass[0] >= 5 and empty.n_stop[0] == 0 and empty.terms["free_space"][0] > 2
    assert car.n_stop[0] >= 5 and car.n_pass[0] == 0 and car.terms["free_space"][0] < -2
    # With the band alone no ray crossed the core of either: free_space 0, the box unjudged by it.
    monkeypatch.setattr(ev, "CORE_Z_OPEN", ev.CORE_Z[1])
    monkeypatch.setattr(ev, "CABIN_FRACTION", ev.CORE_FRACTION[0])
    for scan in (cast([], VLP16), cast([CAR], VLP16)):
        before = evidence(scan, BOX, VLP16)
        assert before.n_pass[0] == before.n_stop[0] == 0 and before.terms["free_space"][0] == 0


def test_a_car_seen_broadside_is_not_called_empty_over_its_bonnet():
    """The cabin is the middle of the length: a ring grazing over a car's bonnet and boot (the
    top of the box is air there) crosses no cabin, so it adds no pass."""
    bonnet = ((32.9, -0.9, GROUND_Z + 0.3), (37.1, 0.9, GROUND_Z + 0.95))  # body to the belt line
    cabin = ((34.2, -0.8, GROUND_Z + 0.95), (35.8, 0.8, GROUND_Z + 1.5))  # roof over the middle
    yawed = Boxes(BOX.center.copy(), BOX.size.copy(), [np.pi / 2], ["Car"], [0.3])  # seen broadside
    bonnet_y = ((33.9, -2.1, GROUND_Z + 0.3), (35.9, 2.1, GROUND_Z + 0.95))
    cabin_y = ((34.2, -0.7, GROUND_Z + 0.95), (35.8, 0.7, GROUND_Z + 1.5))
    for box, parts in ((BOX, [bonnet, cabin]), (yawed, [bonnet_y, cabin_y])):
        car = evidence(cast(parts, VLP16), box, VLP16)
        assert car.n_pass[0] == 0 and car.n_stop[0] > 0, box.yaw
