"""The TraPCC shape-mismatch score and the reject rule."""

from __future__ import annotations

import numpy as np
import pytest
from shapes import box_surface

from pcc_ros.errors import ConfigError
from pcc_ros.pipeline.filter import FilterConfig, map_scores, mcd, mismatch_scores, mismatch_terms, reject_mask


def car_surface(rng: np.random.Generator, n: int = 4000) -> np.ndarray:
    """Points on a car-like canonical box surface: length 1, width 0.42, height 0.38."""
    return box_surface(rng, n, [0.5, 0.21, 0.19]).astype(np.float32)


def test_partial_view_of_the_car_matches_its_completion():
    rng = np.random.default_rng(0)
    car = car_surface(rng)
    visible = car[(car[:, 1] < -0.2) | (car[:, 2] > 0.18)]  # left side and roof: what a LiDAR sees
    mcd, contour = mismatch_terms(visible, car, FilterConfig())
    assert mcd < 0.02 and contour < 0.05
    assert mismatch_scores([visible], [car], FilterConfig())[0] < 0.3


def test_clutter_does_not_match_a_car_completion():
    rng = np.random.default_rng(1)
    car = car_surface(rng)
    pole = np.c_[rng.normal(0, 0.02, (300, 2)), rng.uniform(-0.2, 0.9, 300)].astype(np.float32)
    bush = (rng.normal(0, 0.25, (500, 3)) * [1.0, 1.5, 1.2]).astype(np.float32)
    scores = mismatch_scores([pole, bush], [car, car], FilterConfig())
    assert (scores > 0.5).all()


def test_empty_inputs_are_maximal_mismatch():
    mcd_value, _ = mismatch_terms(np.zeros((0, 3)), np.ones((5, 3)), FilterConfig())
    assert mcd_value == np.inf
    scores = mismatch_scores([np.zeros((0, 3)), np.ones((3, 3))], [np.ones((5, 3)), np.zeros((0, 3))], FilterConfig())
    assert scores.tolist() == [1.0, 1.0]


def test_mcd_is_the_mean_squared_nearest_distance_per_instance():
    partials = [np.array([[0.1, 0, 0], [0.0, 0.2, 0]]), np.array([[0.3, 0, 0]])]
    completions = [np.zeros((1, 3)), np.zeros((1, 3))]  # both at the origin: no cross-talk
    np.testing.assert_allclose(mcd(partials, completions), [(0.01 + 0.04) / 2, 0.09])


def test_reject_only_when_mismatch_high_and_score_low():
    cfg = FilterConfig(match_threshold=0.3, detection_threshold=0.5)
    mismatch = np.array([0.9, 0.9, 0.1, np.nan])
    score = np.array([0.2, 0.8, 0.2, 0.1])
    assert reject_mask(mismatch, score, cfg).tolist() == [True, False, False, False]


def test_logit_scores_are_mapped_explicitly():
    cfg = FilterConfig(score_mapping="sigmoid")
    # PointRCNN logit 2.0 -> 0.88: confident, kept although the shape mismatches.
    assert reject_mask(np.array([0.9, 0.9]), np.array([2.0, -3.0]), cfg).tolist() == [False, True]
    np.testing.assert_allclose(map_scores(np.array([0.0]), "sigmoid"), [0.5])


def test_bad_config_is_refused():
    with pytest.raises(ConfigError, match="score_mapping"):
        FilterConfig(score_mapping="softmax")
