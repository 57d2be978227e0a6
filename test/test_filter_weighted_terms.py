"""The filter measures only what its rule weighs: a term whose weight is 0 is not computed (nor
the pass that only it needs), and the terms that are weighted, and the probability, keep their
values exactly."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scan_scenes import CAR_HI, CAR_LO, GROUND_Z, cast

import pcc_ros.pipeline.evidence as evidence_module
import pcc_ros.pipeline.profile_kernels as profile_kernels
from pcc_ros.pipeline.evidence_profile import PROFILE_TERMS
from pcc_ros.pipeline.filter import TERMS, FilterConfig, false_probability, filter_terms
from pcc_ros.types import Boxes

POLE = ((24.0, 4.9, GROUND_Z), (24.2, 5.1, GROUND_Z + 4.0))
#: on the car, shifted off it, a duplicate of the first, on the pole, on empty ground
BOXES = Boxes([[16.1, 0.0, GROUND_Z + 0.75], [16.1, 1.5, GROUND_Z + 0.75], [16.5, 0.2, GROUND_Z + 0.75],
               [24.1, 5.0, GROUND_Z + 0.75], [30.0, -6.0, GROUND_Z + 0.75]],
              [[4.2, 1.8, 1.5]] * 5, [0.0, 0.0, 0.1, 0.3, -0.5], ["Car"] * 5, [0.9, 0.6, 0.5, 0.7, 0.4])
WEIGHTS = [f"w_{t}" for t in TERMS if t != "mismatch"]


@pytest.fixture(scope="module")
def scan() -> np.ndarray:
    return cast([(CAR_LO, CAR_HI), POLE])


@pytest.fixture
def calls(monkeypatch) -> dict[str, int]:
    """How often each pass runs: the rays, the expected returns, the ground, the profile pass."""
    counts = {"rays": 0, "expected": 0, "ground": 0, "profile": 0}

    def counted(module, name, key):
        original = getattr(module, name)

        def wrapper(*args, **kwargs):
            counts[key] += 1
            return original(*args, **kwargs)

        monkeypatch.setattr(module, name, wrapper)

    counted(evidence_module, "_ray_counts", "rays")
    counted(evidence_module, "_expected_beams", "expected")
    counted(evidence_module, "ground_heights", "ground")
    counted(profile_kernels, "profile_cells", "profile")
    return counts


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("workers", [1, 2])
def test_weighted_terms_and_probability_unchanged(scan, seed, workers):
    rng = np.random.default_rng(seed)
    config = FilterConfig(sensor="hdl64", trees="", **{w: float(rng.normal()) if rng.random() < 0.5 else 0.0
                                                       for w in WEIGHTS})
    full = filter_terms(scan, BOXES, config)
    part = filter_terms(scan, BOXES, config, workers=workers, weighted_only=True)
    assert set(config.weighted_terms) <= set(part)
    for term in config.weighted_terms:
        np.testing.assert_array_equal(part[term], full[term], err_msg=term)
    assert not (set(TERMS) - set(config.weighted_terms) - {"mismatch"}) & set(part)
    np.testing.assert_array_equal(false_probability(part, config), false_probability(full, config))


def test_zero_weights_skip_their_passes(scan, calls):
    zero = dict.fromkeys(WEIGHTS, 0.0)
    # the profile terms alone: no ray, expected-returns or ground pass
    filter_terms(scan, BOXES, FilterConfig(sensor="hdl64", trees="", **{**zero, "w_depth": 1.0}), weighted_only=True)
    assert calls == {"rays": 0, "expected": 0, "ground": 0, "profile": 1}
    # free space alone: the rays; overlap needs no pass over the scan
    filter_terms(scan, BOXES, FilterConfig(sensor="hdl64", trees="", **{**zero, "w_free_space": 1.0, "w_overlap": 1.0}),
                 weighted_only=True)
    assert calls == {"rays": 1, "expected": 0, "ground": 0, "profile": 1}
    terms = filter_terms(scan, BOXES, FilterConfig(sensor="hdl64", trees="", **{**zero, "w_ground_gap": 1.0}),
                         weighted_only=True)
    assert calls == {"rays": 1, "expected": 0, "ground": 1, "profile": 1}
    assert set(terms) == {"ground_gap", "ground_z"}
    # the calibration's default: every pass, every term
    terms = filter_terms(scan, BOXES, FilterConfig(sensor="hdl64", trees="", **zero))
    assert calls == {"rays": 2, "expected": 1, "ground": 2, "profile": 2}
    assert set(TERMS) <= set(terms)


def test_shipped_rule_skips_what_it_does_not_weigh(scan):
    """The shipped weighted sum reads 8 terms; its trees split on every measured term but the detector
    score and the shape, so the node measures those and skips the score and the completion."""
    config = replace(FilterConfig(), sensor="hdl64")
    assert {t for t, w in zip(TERMS, config.weights) if w} == {"density", "free_space", "ground_gap", "above",
                                                                "overlap", "depth", "cover", "corner"}
    assert set(config.weighted_terms) == set(TERMS) - {"score", "mismatch"} == set(config.term_trees.terms)
    terms = filter_terms(scan, BOXES, config, weighted_only=True)
    assert not {"score", "mismatch"} & set(terms)
    assert "cover" in terms and np.all((terms["cover"] >= 0.0) & (terms["cover"] <= 1.0))
    assert set(PROFILE_TERMS) <= set(terms)
    plain = filter_terms(scan, BOXES, replace(config, trees=""), weighted_only=True)
    assert not {"fill", "spill", "top", "score", "through", "n_shell"} & set(plain)


def test_pipeline_measures_weighted_terms_evaluation_all(scan):
    from pcc_ros.pipeline.core import Pipeline, PipelineConfig

    config = PipelineConfig(backend="input", device="cpu", filter=FilterConfig(sensor="hdl64", trees=""))
    pipeline = Pipeline(config)
    node = pipeline.process(scan, BOXES)
    pipeline.all_terms = True
    everything = pipeline.process(scan, BOXES)
    np.testing.assert_array_equal(node.filter_score, everything.filter_score)
    assert "spill" in everything.filter_terms and "spill" not in node.filter_terms
    assert list(node.status) == list(everything.status)


def test_calibration_and_checks_measure_every_term():
    """The rows calibration fits on come from a pipeline that measures every term (a term the
    current rule gives weight 0 must still be measured to be fitted)."""
    from pcc_ros.workflows.detection_eval import build_pipeline
    from pcc_ros.workflows.filter_sensors import measuring_pipeline

    assert measuring_pipeline("", shape=False).all_terms
    assert build_pipeline(None, {"backend": "input"}).all_terms
