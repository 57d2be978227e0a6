"""Far-side and over-time metrics: lateral balance, the unseen half's completeness, consistency,
and the summary the README's real-data table is written from."""

from __future__ import annotations

import numpy as np
import pytest

from pcc_ros.metrics.balance import (
    far_completeness,
    far_half_mask,
    lateral_offset,
    previous_in_track,
    symmetric_chamfer_l1,
    track_consistency,
    track_partners,
)
from pcc_ros.metrics.realdata import real_instance_metrics, symmetric_reference
from pcc_ros.metrics.suite import instance_metrics


def _box_surface(rng: np.random.Generator, n: int = 4000) -> np.ndarray:
    """Points on the faces of a 4.0 x 1.8 x 1.5 m box, canonical units."""
    half = np.array([0.5, 0.9 / 4.0, 0.75 / 4.0])
    pts = rng.uniform(-1, 1, (n, 3)) * half
    axis = rng.integers(0, 3, n)
    pts[np.arange(n), axis] = np.sign(rng.uniform(-1, 1, n)) * half[axis]
    return pts


def test_far_half_is_the_half_away_from_the_sensor():
    pts = np.array([[0.0, 0.2, 0.0], [0.0, -0.2, 0.0], [0.4, 0.0, 0.0], [-0.4, 0.0, 0.0]])
    left = far_half_mask(pts, np.array([0.0, 5.0, 0.4]))  # the sensor on the car's left flank
    assert left.tolist() == [False, True, False, False]
    behind = far_half_mask(pts, np.array([-6.0, 0.0, 0.4]))  # seen from behind: the front is unseen
    assert behind.tolist() == [False, False, True, False]
    assert not far_half_mask(pts, np.array([0.0, 0.0, 3.0])).any()  # straight above: no far half


def test_one_sided_completion_is_lopsided_and_misses_the_far_half():
    rng = np.random.default_rng(0)
    shape = _box_surface(rng)
    origin = np.array([0.0, 4.0, 0.3])  # sensor on +y
    seen = shape[shape[:, 1] > 0]
    assert lateral_offset(shape) < 0.01
    assert lateral_offset(seen) > 0.1
    assert far_completeness(shape, shape, origin) == pytest.approx(0.0, abs=1e-12)
    assert far_completeness(shape, seen, origin) > 0.1  # the far half is not covered by the seen one
    assert np.isnan(far_completeness(seen, shape, origin))  # a reference without far-half points
    size = np.array([4.0, 1.8, 1.5])
    row = real_instance_metrics(seen, seen, shape, size, origin)
    assert row["far_completeness"] > row["completeness"]  # the unseen half is the worse half
    assert np.isnan(real_instance_metrics(seen, seen, shape, size)["far_completeness"])  # needs the origin
    synth = instance_metrics(seen, shape, seen, length=4.0, with_emd=False, origin=origin)
    assert synth["far_coverage"] > synth["coverage"] and synth["lateral_offset"] > 0.1


def test_symmetric_reference_scores_the_flank_a_one_sided_aggregate_lacks():
    rng = np.random.default_rng(1)
    shape = _box_surface(rng)
    origin = np.array([0.0, 4.0, 0.3])  # sensor on +y: the aggregate holds the left flank only
    one_sided = shape[shape[:, 1] > -0.1]
    size = np.array([4.0, 1.8, 1.5])
    lopsided = real_instance_metrics(one_sided, one_sided, one_sided, size, origin)
    whole = real_instance_metrics(shape, one_sided, one_sided, size, origin)
    # the plain one-sided reference cannot tell the two apart on completeness ...
    assert whole["completeness"] == pytest.approx(lopsided["completeness"], abs=1e-9)
    # ... the symmetric one sees the missing right flank, overall and in the unseen half
    assert lopsided["completeness_sym"] > 0.1 > whole["completeness_sym"]
    assert lopsided["far_completeness_sym"] > 0.2 > whole["far_completeness_sym"]
    assert len(symmetric_reference(one_sided)) == 2 * len(one_sided)
    assert np.allclose(symmetric_reference(one_sided)[len(one_sided):, 1], -one_sided[:, 1])


def test_consistency_pairs_consecutive_frames_of_one_track():
    rng = np.random.default_rng(1)
    a = _box_surface(rng, 500)
    shifted = a + np.array([0.0, 0.05, 0.0])
    assert symmetric_chamfer_l1(a, a) == 0.0
    assert symmetric_chamfer_l1(a, shifted) == pytest.approx(0.05, rel=0.3)
    # order scrambled: track t frames 3, 1, 2 and 5 (a gap), track u frame 2, an untracked cloud
    tracks = ["t", "t", "u", "t", "", "t"]
    frames = [3, 1, 2, 2, 4, 5]
    clouds = [shifted, a, a, a, a, a]
    out = track_consistency(tracks, frames, clouds)
    assert np.isnan(out[1]) and np.isnan(out[2]) and np.isnan(out[4])  # first frames, untracked
    assert out[3] == 0.0  # frame 2 against frame 1: the same cloud
    assert out[0] > 0.01  # frame 3 (shifted) against frame 2
    assert np.isnan(out[5])  # frame 5 follows a gap: no pair
    assert track_consistency(tracks, frames, clouds, max_gap=2)[5] > 0.01
    with pytest.raises(ValueError):
        track_consistency(["t"], [1, 2], [a])


def test_previous_in_track_by_frame_any_order():
    # track a at frames 7, 3, 5; b seen once; an empty key has no history
    assert previous_in_track(["a", "b", "a", "", "a"], [7, 2, 3, 4, 5]).tolist() == [4, -1, -1, -1, 2]


def test_summary_rows_use_the_generated_points_and_the_bars():
    from pcc_ros.workflows.evaluate_real import criteria, summary_markdown, summary_rows

    def row(completeness, balance, consistency, learned=True):
        o = {"completeness": completeness, "far_completeness": completeness * 1.2, "lateral_offset": balance,
             "completeness_sym": completeness * 1.5, "far_completeness_sym": completeness * 2.0,
             "consistency": consistency, "consistency_pairs": 3, "count": 4, "fidelity": 0.0,
             "fidelity_generated": 0.1, "spacing": 0.1}
        return {"overall": o, "learned": learned}

    results = {"mirror": row(0.1, 0.0, 0.1, learned=False), "net": row(0.05, 0.3, 0.03),
               "net/generated": row(0.07, 0.05, 0.04), "aggregated GT": row(0.0, 0.3, 0.0, learned=False)}
    rows = {r["backend"]: r for r in summary_rows(results)}
    assert set(rows) == {"mirror", "net"}
    assert rows["net"]["completeness"] == 0.05 and rows["net"]["generated_completeness"] == 0.07
    assert rows["net"]["lateral_balance"] == 0.05 and rows["net"]["consistency"] == 0.04
    assert rows["net"]["generated_gain_vs_mirror"] == pytest.approx(0.3)
    assert rows["mirror"]["generated_completeness"] == 0.1  # a baseline: its own output
    verdict = criteria(results)
    assert set(verdict) == {"net"}
    assert verdict["net"]["completeness_ok"] and not verdict["net"]["generated_ok"]
    assert verdict["net"]["balance_ok"]
    table = summary_markdown(list(rows.values()))
    assert rows["net"]["completeness_sym"] == pytest.approx(0.075) and rows["net"]["far_completeness_sym"] == 0.14
    assert table.count("\n") == 4
    assert "| net | 0.050 | 0.075 | 0.070 (30.0 %) | 0.084 | 0.140 | 0.050 | 0.040 |" in table


def test_track_partners_pair_neighbouring_frames_of_one_car():
    seq = np.array(["0", "0", "0", "0", "1", "0", "1"])
    track = np.array(["a", "a", "b", "a", "a", "", ""])
    frame = np.array([5, 3, 4, 9, 3, 4, 4])
    # a@3 -> a@5, a@5 -> a@9, the last a@9 -> a@5; b and sequence 1's a seen once; untracked: itself
    assert track_partners(seq, track, frame).tolist() == [3, 0, 2, 0, 4, 5, 6]
