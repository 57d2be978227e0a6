"""The filter's profile terms (pcc_ros.pipeline.evidence_profile) on ray-cast scenes where each
term's value is known: a car in its box against a pole, a box shifted off its car, a duplicate;
the ray terms' readings on boxes without evidence (a sunk box, one no ray reaches); ``cover``
on a car, a bin in a car box and a car half hidden behind a wall."""

from __future__ import annotations

import numpy as np
import pytest
from scan_scenes import BOX, CAR_HI, CAR_LO, GROUND_Z, SENSOR, cast

from pcc_ros.pipeline.evidence import COVER_PRIOR, cover
from pcc_ros.pipeline.evidence_profile import (
    ABOVE_PRIOR_RETURNS,
    DEPTH_PRIOR,
    DEPTH_PRIOR_RETURNS,
    covered_share,
    profile_terms,
)
from pcc_ros.pipeline.filter import SENSOR_PRESETS, FilterConfig, evidence, false_probability, filter_terms
from pcc_ros.types import Boxes

CAR = (CAR_LO, CAR_HI)
#: a pole (0.2 m square, 4 m tall) in the middle of the car box
POLE = ((16.0, -0.1, GROUND_Z), (16.2, 0.1, GROUND_Z + 4.0))
#: a pedestrian-sized column (0.5 x 0.5 m, 1.5 m: no taller than the box) at the box's centre
COLUMN = ((15.85, -0.25, GROUND_Z), (16.35, 0.25, GROUND_Z + 1.5))


def terms(targets, boxes=BOX):
    return profile_terms(cast(targets), boxes, SENSOR)


def with_prior(share: float, n_body: float) -> float:
    """``depth`` of ``n_body`` returns at ``share`` of the box depth, with the term's prior returns."""
    return (share * n_body + DEPTH_PRIOR * DEPTH_PRIOR_RETURNS) / (n_body + DEPTH_PRIOR_RETURNS)


def test_above_is_zero_over_a_car_and_most_returns_over_a_pole():
    car, pole = terms([CAR]), terms([POLE])
    assert car["above"][0] == 0.0 and car["n_body"][0] > 100
    # the pole's returns: one per ring and azimuth column on its face; the rings crossing it
    # from the box top to 1.5 m over it, against those from 0.3 m over the bottom to the top
    z = 16.0 * np.tan(SENSOR.ring_elevations())
    top = GROUND_Z + 1.5
    over, body = ((z > top) & (z <= top + 1.5)).sum(), ((z >= GROUND_Z + 0.3) & (z <= top)).sum()
    assert over > 3 and pole["n_above"][0] / (pole["n_above"][0] + pole["n_body"][0]) == pytest.approx(
        over / (over + body), abs=0.05)
    # with the term's prior returns at body height
    n = pole["n_above"][0] + pole["n_body"][0]
    assert pole["above"][0] == pytest.approx(pole["n_above"][0] / (n + ABOVE_PRIOR_RETURNS))


def test_depth_is_near_the_surface_for_a_car_and_deep_for_a_column():
    car, column = terms([CAR]), terms([COLUMN])
    # the car's faces are the box's faces: its returns lie where the rays enter the box
    assert car["depth"][0] < 0.05
    # the column's near face is 0.25 m before the box centre along a ray of 4.2 m of box
    assert column["n_body"][0] > 20
    assert column["depth"][0] == pytest.approx(with_prior((2.1 - 0.25) / 4.2, column["n_body"][0]), abs=0.05)
    assert column["depth"][0] > 0.3
    # an empty box: a car's value, the term says nothing (the ray terms judge it)
    assert terms([])["depth"][0] == DEPTH_PRIOR
    # a handful of deep returns moves it little, dozens move it most of the way
    few = with_prior(0.5, 3)
    assert few < 0.26 < with_prior(0.5, 60)


def test_fill_covers_the_car_silhouette_and_a_sliver_of_it_for_a_pole():
    car, pole, empty = terms([CAR]), terms([POLE]), terms([])
    assert car["fill"][0] > 0.9
    # 0.2 m of the box's 1.8 m width seen at 16 m, widened by one azimuth step each
    assert 0.05 < pole["fill"][0] < 0.2
    assert empty["fill"][0] == 0.0


def test_boxes_shifted_off_their_car():
    on = terms([CAR])
    assert on["n_shell"][0] == 0 and on["spill"][0] < -4
    # a box width across: the car's returns lie in the shell beside the box, a strip inside
    across = Boxes([[16.1, 1.8, GROUND_Z + 0.75]], [[4.2, 1.8, 1.5]], [0.0], ["Car"], [0.3])
    off = terms([CAR], across)
    assert off["n_shell"][0] > 3 * off["n_body"][0] > 0 and off["spill"][0] > on["spill"][0] + 6
    # 2.5 m along, towards the sensor: the car's face (x = 14) lies 2.5 m behind the box's (11.5)
    along = Boxes([[13.6, 0.0, GROUND_Z + 0.75]], [[4.2, 1.8, 1.5]], [0.0], ["Car"], [0.3])
    shifted = terms([CAR], along)
    assert shifted["depth"][0] == pytest.approx(with_prior((2.5 - 0.1) / 4.2, shifted["n_body"][0]), abs=0.05)


def test_overlap_is_the_footprint_share_a_higher_scored_box_covers():
    boxes = Boxes([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 10.0, 0.0]], [[4.0, 2.0, 1.5]] * 3, [0.0] * 3,
                  ["Car"] * 3, [0.9, 0.5, 0.7])
    share = covered_share(boxes)
    assert share.tolist() == pytest.approx([0.0, 0.5, 0.0])
    # equal scores: the earlier box is the better one
    tied = Boxes(boxes.center[:2], boxes.size[:2], boxes.yaw[:2], ["Car"] * 2, [0.5, 0.5])
    assert covered_share(tied).tolist() == pytest.approx([0.0, 0.5])
    # rotated 90 deg on the same centre: a 2 x 2 m square of the 4 x 2 m box
    cross = Boxes(np.zeros((2, 3)), [[4.0, 2.0, 1.5]] * 2, [0.0, np.pi / 2], ["Car"] * 2, [0.9, 0.1])
    assert covered_share(cross)[1] == pytest.approx(0.5, abs=1e-6)


def test_shipped_rule_rejects_the_pole_box_and_keeps_the_car():
    config = FilterConfig()
    car = false_probability(filter_terms(cast([CAR]), BOX, config, sensor=SENSOR), config)[0]
    pole = false_probability(filter_terms(cast([POLE]), BOX, config, sensor=SENSOR), config)[0]
    assert car < config.reject_threshold < pole


def test_no_boxes_and_no_points():
    empty = profile_terms(np.zeros((0, 3), np.float32), BOX, SENSOR)
    assert empty["fill"][0] == 0.0 and empty["depth"][0] == DEPTH_PRIOR and empty["above"][0] == 0.0
    none = profile_terms(cast([CAR]), Boxes(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0)), SENSOR)
    assert all(len(v) == 0 for v in none.values())


def test_two_threads_give_the_same_terms():
    """The profile pass on the filter's second thread beside the evidence: the same values."""
    config = FilterConfig()
    scan = cast([CAR, POLE])
    shift = np.array([[0.5, 0.2, 0.0]])
    boxes = Boxes(np.r_[BOX.center, BOX.center + shift], np.r_[BOX.size, BOX.size], np.r_[BOX.yaw, 0.3],
                  score=np.array([0.9, 0.8]))
    one = filter_terms(scan, boxes, config, sensor=SENSOR, weighted_only=True)
    two = filter_terms(scan, boxes, config, sensor=SENSOR, weighted_only=True, workers=2)
    assert one.keys() == two.keys() and {"depth", "above", "overlap"} <= one.keys()
    for k in one:
        np.testing.assert_array_equal(one[k], two[k])
    assert two["overlap"][1] > 0  # the second box is covered by the better-scored first


# ---- the ray terms' evidence-only readings (pcc_ros.pipeline.evidence)

def test_sunk_box_has_no_ground_gap():
    """A box whose bottom lies below the local ground: no evidence against it (where no beam
    reaches the road the lowest returns around a car are kerbs and bodies, above its bottom)."""
    sunk = Boxes([[16.1, 0.0, GROUND_Z - 0.25]], [[4.2, 1.8, 1.5]], [0.0])
    ev = evidence(cast([]), sunk)
    assert ev.ground_z[0] == pytest.approx(GROUND_Z, abs=0.05) and ev.terms["ground_gap"][0] == 0.0


def test_through_is_the_share_of_a_cars_returns_that_pass():
    """``through``: 0 on a car and on a box no ray reaches; on an empty box the rays through
    its core over what a car would return, whatever the sensor's resolution."""
    car = evidence(cast([CAR]), BOX)
    assert car.terms["through"][0] == 0.0
    wall = ((8.0, -4.0, GROUND_Z), (8.3, 4.0, 3.0))
    assert evidence(cast([wall]), BOX).terms["through"][0] == 0.0
    shares = []
    for name in ("hdl64", "vlp16", "os1_64"):
        sensor = SENSOR_PRESETS[name]
        empty = evidence(cast([], sensor), BOX, sensor)
        expect = empty.n_pass[0] / (empty.expected[0] + 1.0)  # nothing occludes it
        assert empty.terms["through"][0] == pytest.approx(expect) and empty.n_pass[0] > 0
        shares.append(empty.terms["through"][0])
    # the core is 0.8 x 0.8 x 0.4 of the box: about a third of the beams that meet the box
    assert all(0.15 < v < 0.6 for v in shares), shares



# ---- cover: the share of the box's unhidden azimuth columns holding a return

#: a bin (0.6 m square, 1.1 m tall) at the near end of the car box
BIN = ((14.0, -0.3, GROUND_Z), (14.6, 0.3, GROUND_Z + 1.1))
#: a wall in front of the car box hiding the half of its azimuth interval at y < 0
SCREEN = ((8.0, -3.0, GROUND_Z), (8.3, 0.0, GROUND_Z + 3.0))


def test_cover_counts_the_columns_nothing_in_front_hides():
    """A car fills every azimuth column of its box; a bin in the car box fills a few, the rays
    beside it crossing the core to the wall behind; a car half behind a wall fills every column
    the wall leaves it (the hidden ones are not counted against it); an empty box fills none."""
    def cover_of(targets):
        ev = evidence(cast(targets), BOX, columns=True)
        return ev.terms["n_filled"][0], ev.terms["n_seen"][0], ev.terms["cover"][0]

    car, bin_, hidden, empty = (cover_of(t) for t in ([CAR], [BIN], [CAR, SCREEN], []))
    assert car[1] > 30 and car[0] >= 0.95 * car[1]
    # (the columns at the box's sides, beside its core, count only where something fills them)
    assert bin_[1] >= 0.6 * car[1] and bin_[0] < 0.5 * bin_[1]
    assert 0.3 * car[1] < hidden[1] < 0.7 * car[1] and hidden[0] >= 0.95 * hidden[1]
    assert empty[0] == 0 and empty[1] == bin_[1]
    assert min(car[2], hidden[2]) > bin_[2] + 0.1 > empty[2] + 0.1
    assert car[2] == pytest.approx(cover(np.array([car[0]]), np.array([car[1]]))[0])


def test_cover_without_columns_keeps_a_cars_value():
    """A box no ray reaches (nothing seen) reads the prior, a car's value: no evidence."""
    far = Boxes([[16.1, 30.0, GROUND_Z + 20.75]], [[4.2, 1.8, 1.5]], [0.0])  # above every beam
    ev = evidence(cast([CAR]), far, columns=True)
    assert ev.terms["n_seen"][0] == 0 and ev.terms["cover"][0] == pytest.approx(COVER_PRIOR)


def test_cover_is_measured_only_where_weighted():
    """Weight 0: the node does not measure it; a weight (the shipped rule's): it does, the same values."""
    scan = cast([CAR])
    assert FilterConfig().w_cover != 0.0  # the shipped rule weighs it
    unweighted = FilterConfig(w_cover=0.0, trees="")
    assert "cover" not in filter_terms(scan, BOX, unweighted, sensor=SENSOR, weighted_only=True)
    weighted = filter_terms(scan, BOX, FilterConfig(trees=""), sensor=SENSOR, weighted_only=True)
    every = filter_terms(scan, BOX, FilterConfig(w_cover=0.0, trees=""), sensor=SENSOR)
    assert weighted["cover"][0] == every["cover"][0] > 0.9
