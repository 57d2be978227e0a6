"""Metric values against hand-computed cases and a brute-force NumPy reference."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from pcc_ros.metrics import (
    METRICS,
    chamfer,
    chamfer_batch,
    chamfer_l1,
    chamfer_l2,
    emd,
    emd_exact,
    fidelity,
    fscore,
    fscore_at_percent,
    instance_metrics,
    nearest_distances,
    one_sided,
    side_length,
    side_view_cd,
    to_metres,
    unit_label,
)


def brute_nn(a, b):
    """Reference: full distance matrix, min over targets."""
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    return np.sqrt(((a[:, None, :] - b[None, :, :]) ** 2).sum(-1)).min(axis=1)


def test_hand_computed_chamfer():
    pred = np.array([[0.0, 0, 0], [1, 0, 0]])
    truth = np.array([[0.0, 0, 0], [3, 0, 0]])
    # pred -> truth: 0, 1 ; truth -> pred: 0, 2
    r = chamfer(pred, truth)
    assert r["precision"] == pytest.approx(0.5)
    assert r["coverage"] == pytest.approx(1.0)
    assert r["cd_l1"] == pytest.approx(0.75)
    assert r["precision_l2"] == pytest.approx(0.5)
    assert r["coverage_l2"] == pytest.approx(2.0)
    assert r["cd_l2"] == pytest.approx(2.5)
    assert chamfer_l1(pred, truth) == pytest.approx(0.75)
    assert chamfer_l2(pred, truth) == pytest.approx(2.5)
    assert one_sided(truth, pred, squared=True) == pytest.approx(2.0)
    assert chamfer(truth, truth)["cd_l1"] == 0.0


@pytest.mark.parametrize("seed", range(4))
def test_chamfer_matches_brute_force(seed):
    rng = np.random.default_rng(seed)
    pred = rng.normal(size=(rng.integers(1, 300), 3))
    truth = rng.normal(size=(rng.integers(1, 300), 3)) * 0.7 + 0.1
    np.testing.assert_allclose(nearest_distances(pred, truth), brute_nn(pred, truth), rtol=1e-12)
    d1, d2 = brute_nn(pred, truth), brute_nn(truth, pred)
    r = chamfer(pred, truth)
    assert r["cd_l1"] == pytest.approx((d1.mean() + d2.mean()) / 2, rel=1e-12)
    assert r["cd_l2"] == pytest.approx((d1**2).mean() + (d2**2).mean(), rel=1e-12)
    batch = chamfer_batch([pred, truth], [truth, pred])
    assert batch["precision"][0] == pytest.approx(d1.mean()) and batch["coverage"][1] == pytest.approx(d1.mean())


def test_chamfer_rejects_bad_input():
    with pytest.raises(ValueError, match="non-empty"):
        chamfer(np.zeros((0, 3)), np.zeros((2, 3)))
    with pytest.raises(ValueError, match="dimension mismatch"):
        nearest_distances(np.zeros((2, 2)), np.zeros((2, 3)))


def test_fscore_hand_computed():
    pred = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [10, 0, 0]])
    truth = np.array([[0.0, 0, 0], [1.05, 0, 0]])
    # threshold 0.1: pred matched 2/4 = 0.5; truth matched 2/2 = 1 -> F = 2*0.5/(1.5)
    assert fscore(pred, truth, 0.1) == pytest.approx(2 / 3)
    assert fscore(pred, truth, 0.01) == pytest.approx(2 * 0.25 * 0.5 / 0.75)
    # boundary: distance exactly equal to the threshold counts as matched
    assert fscore(np.array([[0.0, 0, 0]]), np.array([[0.5, 0, 0]]), 0.5) == 1.0
    assert fscore(np.array([[0.0, 0, 0]]), np.array([[5.0, 0, 0]]), 0.5) == 0.0
    # @1%: side length of the prediction = 10 -> threshold 0.1
    assert side_length(pred) == 10.0
    assert fscore_at_percent(pred, truth) == pytest.approx(2 / 3)
    # with the truth's side (1.05) the threshold is 0.0105: exact matches only
    assert fscore_at_percent(pred, truth, reference="truth") == pytest.approx(2 * 0.25 * 0.5 / 0.75)


def test_fscore_matches_brute_force():
    rng = np.random.default_rng(7)
    pred, truth = rng.uniform(size=(400, 3)), rng.uniform(size=(500, 3))
    t = 0.05
    p = (brute_nn(pred, truth) <= t).mean()
    r = (brute_nn(truth, pred) <= t).mean()
    assert fscore(pred, truth, t) == pytest.approx(2 * p * r / (p + r))


def test_emd_exact_small_cases():
    a = np.array([[0.0, 0, 0], [1, 0, 0]])
    b = np.array([[1.0, 0, 1], [0, 0, 1]])
    assert emd_exact(a, b) == pytest.approx(1.0)  # crossing avoided: each point moves up by 1
    # permutation invariance and exact optimum against enumeration of all bijections
    rng = np.random.default_rng(3)
    a, b = rng.normal(size=(6, 3)), rng.normal(size=(6, 3))
    best = min(np.linalg.norm(a - b[list(p)], axis=1).mean() for p in itertools.permutations(range(6)))
    assert emd_exact(a, b) == pytest.approx(best)
    assert emd_exact(a[::-1], b) == pytest.approx(best)
    # a rigid translation by t moves every point by |t|
    assert emd(a, a + np.array([0.3, 0.4, 0]), seed=1) == pytest.approx(0.5)


def test_emd_subsamples_reproducibly():
    rng = np.random.default_rng(4)
    a, b = rng.normal(size=(3000, 3)), rng.normal(size=(2000, 3))
    e1 = emd(a, b, max_points=256, seed=5)
    assert e1 == emd(a, b, max_points=256, seed=5)
    assert e1 > 0
    # same distribution: EMD shrinks as the subsample grows (estimate of a vanishing quantity)
    assert emd(a, b, max_points=1024, seed=5) < e1


def test_gt_free_metrics():
    partial = np.array([[0.0, 0, 0], [1, 0, 0]])
    completion = np.array([[0.0, 0, 0], [1, 0, 0.5], [5, 5, 5]])
    assert fidelity(partial, completion) == pytest.approx((0 + 0.25) / 2)
    # side view drops y: these two clouds differ only in y -> 0
    a = np.array([[0.1, 0.3, 0.2], [0.4, -0.2, 0.0]])
    b = a * [1, -1, 1] + [0, 0.5, 0]
    assert side_view_cd(a, b) == 0.0
    c = a + np.array([0, 0, 0.1])
    assert side_view_cd(a, c) == pytest.approx(0.01 + 0.01)
    rng = np.random.default_rng(9)
    p, q = rng.normal(size=(50, 3)), rng.normal(size=(60, 3))
    ref = (brute_nn(p[:, [0, 2]], q[:, [0, 2]]) ** 2).mean() + (brute_nn(q[:, [0, 2]], p[:, [0, 2]]) ** 2).mean()
    assert side_view_cd(p, q) == pytest.approx(ref)


def test_units_and_instance_metrics():
    assert unit_label("cd_l1", metres=True) == "m"
    assert unit_label("cd_l2", metres=True) == "m^2"
    assert unit_label("cd_l2", metres=False) == "canon^2"
    assert unit_label("fscore", metres=True) == "-"
    assert to_metres("cd_l2", 0.01, 4.0) == pytest.approx(0.16)
    assert to_metres("fscore", 0.5, 4.0) == 0.5
    # metres computed directly in a scaled copy == canonical value converted
    rng = np.random.default_rng(11)
    pred, truth, partial = rng.normal(size=(300, 3)), rng.normal(size=(400, 3)), rng.normal(size=(50, 3))
    length = 4.2
    pseudo = {"whole": rng.normal(size=(200, 3)), "front": rng.normal(size=(80, 3)) + 0.5, "back": None}
    origin = np.array([1.0, 5.0, 0.4])
    canon = instance_metrics(pred, truth, partial, length=length, emd_points=128, seed=2, pseudo_gt=pseudo,
                             origin=origin)
    direct = instance_metrics(pred * length, truth * length, partial * length, length=1.0, emd_points=128, seed=2,
                              fixed_threshold_m=0.05,
                              pseudo_gt={k: None if v is None else v * length for k, v in pseudo.items()},
                              origin=origin * length)
    for key in ("cd_l1", "cd_l2", "precision", "coverage", "emd", "fidelity", "side_cd", "l_g", "l_i", "l_s",
                "mean_cd", "far_coverage", "lateral_offset"):
        assert to_metres(key, canon[key], length) == pytest.approx(direct[key], rel=1e-9), key
    assert canon["fscore"] == pytest.approx(direct["fscore"])
    assert set(METRICS) - set(canon) == {"consistency"}  # spans two frames: the evaluation adds it
    with pytest.raises(ValueError):
        instance_metrics(pred, truth, length=0.0)
