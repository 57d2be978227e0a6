"""The evidence terms of the detection filter on constructed scenes, and the calibration."""

from __future__ import annotations

import numpy as np
import pytest
from scan_scenes import BOX, CAR_HI, CAR_LO, GROUND_Z, SENSOR, cast

from pcc_ros.errors import ConfigError
from pcc_ros.pipeline.filter import (
    RULE_WEIGHTS,
    SENSOR_PRESETS,
    FilterConfig,
    evidence,
    false_probability,
    filter_terms,
    mismatch_scores,
    score_logit,
)
from pcc_ros.types import Boxes


def test_free_space_empty_box_vs_box_with_a_car():
    empty_scan = cast([])
    car_scan = cast([(CAR_LO, CAR_HI)])
    empty, car = evidence(empty_scan, BOX), evidence(car_scan, BOX)
    # Rays through the empty box return from the ground and wall behind it...
    assert empty.n_pass[0] > 50 and empty.n_stop[0] == 0 and empty.n_in[0] == 0
    # ... those through the car end on it.
    assert car.n_stop[0] > 50 and car.n_pass[0] == 0 and car.n_in[0] > 100
    assert empty.terms["free_space"][0] > 4 and car.terms["free_space"][0] < -4
    # Returns vs a car's: the car gives about what the beam model expects of its box.
    assert car.terms["density"][0] > -1.0 > empty.terms["density"][0] + 3
    # Both stand on the ground.
    assert empty.terms["ground_gap"][0] < 0.1 and car.terms["ground_gap"][0] < 0.1


def test_occluded_box_is_not_called_empty():
    """A wall between the sensor and the box: no ray reaches it, so no free-space evidence and
    no expected returns (the occluded share of the rays is discounted)."""
    wall = ((8.0, -4.0, GROUND_Z), (8.3, 4.0, 3.0))
    ev = evidence(cast([wall]), BOX)
    assert ev.n_pass[0] == 0 and ev.n_stop[0] == 0 and ev.n_occluded[0] > 50
    assert abs(ev.terms["free_space"][0]) < 1e-9
    assert abs(ev.terms["density"][0]) < 0.5  # expected * visible ~ 0: nothing is missing


def test_floating_box_has_a_ground_gap():
    lifted = Boxes([[16.1, 0.0, GROUND_Z + 2.75]], [[4.2, 1.8, 1.5]], [0.0])
    ev = evidence(cast([]), lifted)
    assert ev.terms["ground_gap"][0] == pytest.approx(2.0, abs=0.1)


def test_expected_returns_follow_the_beam_geometry():
    """Twice the range: about half the rings and half the columns cross the box."""
    near = Boxes([[15.0, 0.0, GROUND_Z + 0.75]], [[4.0, 1.8, 1.5]], [np.pi / 2])  # broadside
    far = Boxes([[30.0, 0.0, GROUND_Z + 0.75]], [[4.0, 1.8, 1.5]], [np.pi / 2])
    e_near, e_far = evidence(np.zeros((1, 3), np.float32), near), evidence(np.zeros((1, 3), np.float32), far)
    assert 2.5 < e_near.expected[0] / e_far.expected[0] < 6.0
    coarse = evidence(np.zeros((1, 3), np.float32), near, SENSOR_PRESETS["hdl32"])
    assert coarse.expected[0] < e_near.expected[0] / 2


def test_nan_points_and_no_boxes():
    scan = cast([(CAR_LO, CAR_HI)])
    scan[::7] = np.nan
    ev = evidence(scan, BOX)
    assert np.isfinite(ev.terms["density"]).all() and ev.n_in[0] > 50
    assert len(evidence(scan, Boxes.empty()).n_in) == 0


def test_a_second_thread_measures_the_same_evidence():
    scan = cast([(CAR_LO, CAR_HI), ((25.0, 3.0, GROUND_Z + 0.3), (29.0, 4.8, GROUND_Z + 1.4))])
    boxes = Boxes([[16.1, 0.0, GROUND_Z + 0.75], [27.0, 3.9, GROUND_Z + 0.8], [22.0, -6.0, GROUND_Z + 0.7]],
                  [[4.2, 1.8, 1.5], [4.0, 1.8, 1.6], [4.4, 1.9, 1.4]], [0.0, 0.3, -1.2], ["Car"] * 3, [0.3] * 3)
    one, two = evidence(scan, boxes).as_dict(), evidence(scan, boxes, workers=2).as_dict()
    assert one.keys() == two.keys()
    for key in one:
        np.testing.assert_array_equal(one[key], two[key])
    assert np.isfinite(one["ground_z"]).all() and (one["n_in"][:2] > 20).all()


def test_probability_combines_terms_with_the_configured_weights():
    config = FilterConfig(w_bias=-1.0, w_density=-1.0, w_free_space=0.5, w_ground_gap=2.0, w_score=-0.5, trees="")
    terms = {"density": np.array([0.0, -3.0]), "free_space": np.array([-5.0, 4.0]),
             "ground_gap": np.array([0.0, 0.0]), "score": np.array([2.0, 0.0]), "mismatch": np.array([np.nan, 0.2])}
    z = np.array([-1.0 + 0.0 - 2.5 + 0 - 1.0, -1.0 + 3.0 + 2.0])
    assert false_probability(terms, config) == pytest.approx(1 / (1 + np.exp(-z)))
    assert score_logit(np.array([0.0]), "sigmoid")[0] == 0.0
    assert score_logit(np.array([0.5]), "identity")[0] == pytest.approx(0.0)
    with pytest.raises(ConfigError):
        FilterConfig(rule="vote")
    with pytest.raises(ConfigError):
        FilterConfig(reject_threshold=1.0)


def test_shipped_filter_rejects_the_empty_box_and_keeps_the_car():
    config = FilterConfig()  # the calibrated KITTI defaults
    for scan, false in ((cast([]), True), (cast([(CAR_LO, CAR_HI)]), False)):
        terms = filter_terms(scan, BOX, config)
        assert (false_probability(terms, config)[0] > config.reject_threshold) == false


def test_filter_config_defaults_equal_the_shipped_yaml():
    """Two copies that must agree: FilterConfig's defaults (what ``pcc replay`` and the library
    use) and config/detection_filter.yaml (what the node loads). This says nothing of the weights'
    worth: that is measured against independent baselines on labelled real frames
    (test_filter_calibration.py: the shipped threshold against points-in-box and the detector
    score) and, for a fit, by calibrate-filter's leave-frames-out folds."""
    from pathlib import Path

    from pcc_ros.pipeline.config import read_parameters

    shipped = read_parameters(Path(__file__).resolve().parents[1] / "config" / "detection_filter.yaml")
    defaults = FilterConfig()
    for key in ("w_bias", *RULE_WEIGHTS, "mismatch_mean", "reject_threshold", "sensor", "rule"):
        assert shipped[key] == getattr(defaults, key), key


def test_node_publishes_scores_terms_markers_and_counts():
    """A filter node on a physically cast scene: a car and an empty box. The kept / rejected
    detections carry the probability and the terms as extra hypotheses; the detector's own
    hypothesis still decodes as the label and score; RViz text and /diagnostics counts."""
    from pcc_ros.msg.detections import boxes_from_detection_array, detection_array_from_boxes
    from pcc_ros.msg.pointcloud2 import create_cloud
    from pcc_ros.msg.typestore import get_typestore
    from pcc_ros.runtime.base import RELIABLE, SENSOR_DATA
    from pcc_ros.runtime.local import LocalGraph, LocalRuntime
    from pcc_ros.runtime.node import NodeCore

    scan = cast([(CAR_LO, CAR_HI)])
    boxes = Boxes([[16.1, 0.0, GROUND_Z + 0.75], [25.0, -8.0, GROUND_Z + 0.75]], [[4.2, 1.8, 1.5]] * 2,
                  [0.0, 0.3], ["Car", "Car"], [0.6, 0.6], ["car", "empty"])
    graph = LocalGraph(simulated=True)
    NodeCore(LocalRuntime(graph, "filter_node"), "filter_node", "filter", {"backend": "input"}, threaded=False)
    got: dict[str, list] = {"kept": [], "rejected": [], "markers": [], "diag": []}
    probe = LocalRuntime(graph, "probe")
    dets_t = "vision_msgs/msg/Detection3DArray"
    probe.create_subscription("/detections_filtered", dets_t, got["kept"].append, RELIABLE)
    probe.create_subscription("/detections_rejected", dets_t, got["rejected"].append, RELIABLE)
    probe.create_subscription("/filter_markers", "visualization_msgs/msg/MarkerArray", got["markers"].append, RELIABLE)
    probe.create_subscription("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray", got["diag"].append, RELIABLE)
    driver = LocalRuntime(graph, "driver")
    driver.create_publisher("/points", "sensor_msgs/msg/PointCloud2", SENSOR_DATA).publish(
        create_cloud(scan, ["x", "y", "z"], "velodyne", 1_000_000_000))
    driver.create_publisher("/detections", dets_t, RELIABLE).publish(
        detection_array_from_boxes(boxes, "velodyne", 1_000_000_000))
    graph.advance_to(1_500_000_000)
    kept, rejected = got["kept"][0].detections, got["rejected"][0].detections
    assert [d.id for d in kept] == ["car"] and [d.id for d in rejected] == ["empty"]
    for det, false in ((kept[0], False), (rejected[0], True)):
        ids = [r.hypothesis.class_id for r in det.results]
        assert ids[0] == "Car" and ids[1] == "pcc_filter_score"
        # the terms the shipped rule weighs; one it gives weight 0 is not measured, not published
        assert {f"pcc_filter/{t}" for t in FilterConfig().weighted_terms} <= set(ids)
        assert "pcc_filter/density" in ids and "pcc_filter/cover" in ids and "pcc_filter/score" not in ids
        p = det.results[1].hypothesis.score
        assert (p > FilterConfig().reject_threshold) == false
    decoded = boxes_from_detection_array(got["kept"][0])
    assert decoded.label.tolist() == ["Car"] and decoded.score.tolist() == [0.6]  # filter hypotheses skipped
    get_typestore().serialize_cdr(got["kept"][0], dets_t)  # valid on the wire
    texts = [m.text for m in got["markers"][0].markers if m.text]
    assert any("p_false" in t and "kept" in t for t in texts) and any("rejected" in t for t in texts)
    values = {kv.key: kv.value for kv in got["diag"][-1].status[0].values}
    assert values["detections_kept"] == "1" and values["detections_rejected"] == "1"


def _brute_force_rays(scan: np.ndarray, boxes: Boxes) -> dict[str, np.ndarray]:
    """n_in / n_occluded / n_stop / n_pass / n_rays by testing every point against every judged
    box (no index), with the float64 slab arithmetic the filter documents."""
    from pcc_ros.geometry.canonical import to_box_local
    from pcc_ros.pipeline.evidence import EVIDENCE_GROUND, angular_window, core_box

    judged = angular_window(boxes)[4]
    core_lo, core_hi = core_box(boxes, SENSOR)  # the documented core (the cabin where no ring crosses the band)
    p = scan[:, :3].astype(np.float64)
    out = {k: np.zeros(len(boxes)) for k in ("n_in", "n_occluded", "n_stop", "n_pass", "n_rays")}
    for b in np.flatnonzero(judged):  # a test: one box at a time
        c, s = np.cos(boxes.yaw[b]), np.sin(boxes.yaw[b])
        origin = np.array(to_box_local(0.0, 0.0, 0.0, *boxes.center[b], c, s))
        local = to_box_local(p[:, 0], p[:, 1], p[:, 2], *boxes.center[b], c, s)
        d = [local[a] - origin[a] for a in range(3)]
        half = boxes.size[b] / 2
        body = (np.array([-half[0], -half[1], -half[2] + EVIDENCE_GROUND]), half)
        core = (core_lo[b], core_hi[b])
        t = {}
        with np.errstate(divide="ignore", invalid="ignore"):
            for name, (lo, hi) in (("body", body), ("core", core)):
                tmin = tmax = None
                for a in range(3):
                    inv = 1.0 / d[a]
                    t1, t2 = (lo[a] - origin[a]) * inv, (hi[a] - origin[a]) * inv
                    near, far = np.minimum(t1, t2), np.maximum(t1, t2)
                    tmin = near if tmin is None else np.fmax(tmin, near)
                    tmax = far if tmax is None else np.fmin(tmax, far)
                t[name] = (tmin, tmax)
            (tin, tout), (cin, cout) = t["body"], t["core"]
            through = tout >= np.maximum(tin, 0.0)
            core_hit = through & (cout >= np.maximum(cin, 0.0))
            out["n_rays"][b] = through.sum()
            out["n_in"][b] = (through & (tin <= 1.0) & (1.0 <= tout)).sum()
            out["n_occluded"][b] = (through & (1.0 < tin)).sum()
            out["n_stop"][b] = (core_hit & (tin <= 1.0) & (1.0 <= cout)).sum()
            out["n_pass"][b] = (core_hit & (1.0 > cout)).sum()
    return out


def _brute_force_ground(scan: np.ndarray, boxes: Boxes) -> np.ndarray:
    """The local ground by its definition: the 5 % quantile of the z of the points that
    geometry.boxes.points_in_boxes finds in the boxes widened by the sensor's ground reach."""
    from pcc_ros.geometry.boxes import points_in_boxes
    from pcc_ros.pipeline.evidence import ground_reach

    n = len(boxes)
    reach = ground_reach(boxes, SENSOR)[:, None]
    bottom = boxes.center[:, 2] - boxes.size[:, 2] / 2
    wide = Boxes(np.c_[boxes.center[:, :2], bottom - 1.0],
                 np.c_[boxes.size[:, :2] + 2 * reach, np.full(n, 4.0)], boxes.yaw)
    out = np.full(n, np.nan)
    for b, idx in enumerate(points_in_boxes(scan, wide)):
        if len(idx):
            k = int(0.05 * (len(idx) - 1))
            out[b] = np.partition(scan[idx, 2], k)[k]
    return out


def _scattered_scene(seed: int, dtype=np.float32):
    """Random returns all around the sensor (both sides of the +-pi seam), NaN rows, a return
    at the sensor itself (paired, as arctan2(0, 0) = 0, with the box at azimuth and elevation 0),
    and boxes near and far, overlapping, yawed, one around the sensor."""
    rng = np.random.default_rng(seed)
    scan = rng.uniform(-40.0, 40.0, (20_000, 3)).astype(dtype)
    scan[:, 2] = rng.uniform(-2.5, 1.5, len(scan))
    scan[::97] = np.nan
    scan[5] = 0.0
    boxes = Boxes([[-20.0, 0.3, -1.0], [-18.0, -0.4, -0.9], [10.0, 12.0, -1.0], [5.0, -30.0, -0.8],
                   [11.0, 12.5, -0.9], [0.5, 0.2, -1.0], [-39.0, 38.0, -1.1], [8.0, 0.2, -0.4]],
                  [[4.2, 1.8, 1.5], [4.0, 1.8, 1.6], [4.4, 1.9, 1.4], [4.5, 1.8, 1.5], [4.1, 1.7, 1.5],
                   [4.0, 1.8, 1.5], [4.6, 2.0, 1.7], [3.9, 1.7, 1.4]],
                  np.r_[rng.uniform(-np.pi, np.pi, 7), -np.pi / 2], ["Car"] * 8, [0.5] * 8)
    return scan, boxes


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_ray_and_ground_indexes_equal_testing_every_point_against_every_box(dtype):
    """The ray index (azimuth x slope cells) and the ground query's BEV grid only choose which
    (point, box) pairs get the exact test: the counts and ground heights equal the exact test on
    every pair, across the +-pi seam, with NaN rows and a return at the sensor."""
    for seed in (3, 4):
        scan, boxes = _scattered_scene(seed, dtype)
        ev = evidence(scan, boxes).as_dict()
        brute = _brute_force_rays(scan, boxes)
        assert brute["n_rays"].sum() > 500 and brute["n_pass"].sum() > 0 and brute["n_in"].sum() > 0
        for key, value in brute.items():
            np.testing.assert_array_equal(ev[key], value, err_msg=key)
        np.testing.assert_array_equal(ev["ground_z"], _brute_force_ground(scan, boxes))
        assert ev["n_rays"][5] == 0  # the box around the sensor is not judged


def test_ground_reach_widens_with_the_ring_spacing_of_the_sensor():
    """Near boxes and dense sensors keep the 3 m reach; a sparse sensor's rings meet the road
    metres apart at range, so the reach grows to half that spacing (capped)."""
    from pcc_ros.pipeline.evidence import GROUND_REACH, GROUND_REACH_MAX, ground_reach

    d = np.array([8.0, 20.0, 30.0, 60.0])
    boxes = Boxes(np.c_[d, np.zeros(4), np.full(4, -0.98)], np.tile([4.2, 1.8, 1.5], (4, 1)), np.zeros(4))
    hdl64, vlp16 = ground_reach(boxes, SENSOR), ground_reach(boxes, SENSOR_PRESETS["vlp16"])
    np.testing.assert_array_equal(hdl64[:3], GROUND_REACH)
    assert GROUND_REACH < hdl64[3] < GROUND_REACH_MAX
    # VLP-16 at 20 m: rings -3 and -5 deg seen from 1.73 m meet the road 33.0 and 19.8 m away
    h = 1.73
    assert vlp16[1] == pytest.approx((h / np.tan(np.deg2rad(3)) - h / np.tan(np.deg2rad(5))) / 2, rel=0.02)
    assert vlp16[0] == GROUND_REACH and vlp16[3] == GROUND_REACH_MAX


def test_expected_beams_equal_a_beam_by_beam_count():
    from pcc_ros.geometry.canonical import to_box_local
    from pcc_ros.pipeline.evidence import EVIDENCE_GROUND, EXPECTED_COLUMNS, angular_window

    _, boxes = _scattered_scene(3)
    got = evidence(np.zeros((0, 3), np.float32), boxes).expected
    az_lo, az_hi, el_lo, el_hi, judged = angular_window(boxes)
    rings = SENSOR.ring_elevations()
    step = np.deg2rad(SENSOR.azimuth_resolution_deg)
    for b in range(len(boxes)):
        if not judged[b]:
            assert got[b] == 0
            continue
        full = int(np.floor((az_hi[b] - az_lo[b]) / step)) + 1
        cols = min(full, EXPECTED_COLUMNS)
        az = az_lo[b] + (np.arange(cols) + 0.5) * step * (full / cols)
        el = rings[(rings >= el_lo[b]) & (rings <= el_hi[b])]
        e, a = np.meshgrid(el, az, indexing="ij")
        c, s = np.cos(boxes.yaw[b]), np.sin(boxes.yaw[b])
        d = to_box_local(np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e), 0.0, 0.0, 0.0, c, s)
        origin = np.array(to_box_local(0.0, 0.0, 0.0, *boxes.center[b], c, s))
        half = boxes.size[b] / 2
        lo = np.array([-half[0], -half[1], -half[2] + EVIDENCE_GROUND]) - origin
        hi = half - origin
        with np.errstate(divide="ignore", invalid="ignore"):
            t1 = [lo[k] / d[k] for k in range(3)]
            t2 = [hi[k] / d[k] for k in range(3)]
        tmin = np.fmax.reduce([np.minimum(p, q) for p, q in zip(t1, t2)])
        tmax = np.fmin.reduce([np.maximum(p, q) for p, q in zip(t1, t2)])
        hits = (tmax >= np.maximum(tmin, 0.0)).sum()
        assert got[b] == pytest.approx(hits * full / cols, rel=1e-12, abs=1e-9), b
        assert hits > 0 or el.size == 0


def test_empty_scans_and_boxes_without_points():
    """No points, only NaN points, a box far from every return: zero counts, no ground (the
    gap term reads 0), finite terms; no boxes: empty rows."""
    _, boxes = _scattered_scene(3)
    nan_scan = np.full((50, 3), np.nan, np.float32)
    for scan in (np.zeros((0, 3), np.float32), nan_scan, np.zeros((0, 4))):
        ev = evidence(scan, boxes).as_dict()
        for key in ("n_in", "n_stop", "n_pass", "n_occluded", "n_rays"):
            assert (ev[key] == 0).all(), key
        assert np.isnan(ev["ground_z"]).all() and (ev["ground_gap"] == 0).all()
        assert all(np.isfinite(ev[k]).all() for k in ("density", "free_space"))
        assert (ev["expected"][angular_window_judged(boxes)] > 0).any()
    far = Boxes([[60.0, -50.0, -0.9]], [[4.2, 1.8, 1.5]], [0.4])
    ev = evidence(cast([(CAR_LO, CAR_HI)]), far)
    assert ev.n_in[0] == 0 and np.isnan(ev.ground_z[0]) and ev.terms["ground_gap"][0] == 0
    empty = evidence(cast([]), Boxes.empty()).as_dict()
    assert all(len(v) == 0 for v in empty.values())


def angular_window_judged(boxes: Boxes) -> np.ndarray:
    from pcc_ros.pipeline.evidence import angular_window

    return angular_window(boxes)[4]


def test_bad_input_is_a_clear_error():
    from pcc_ros.errors import DataError

    with pytest.raises(DataError, match="points must be"):
        evidence(np.zeros((10, 2), np.float32), BOX)
    bad = Boxes([[16.1, 0.0, np.nan]], [[4.2, 1.8, 1.5]], [0.0])
    with pytest.raises(DataError, match="box 0 is invalid"):
        evidence(cast([]), bad)


def test_mismatch_work_runs_only_when_its_weight_is_non_zero():
    """The shape-mismatch term costs a completion per box; with ``w_mismatch`` 0 (the shipped
    presets) the pipeline neither loads the ``filter_backend`` nor completes for it, with a non-zero
    weight it loads that second backend (mirror beside the pipeline's input) and completes the
    boxes with it: the mismatch is the mirror's, not the pipeline's own backend's."""
    from pcc_ros.models.baselines import InputCompleter, MirrorCompleter
    from pcc_ros.pipeline.core import Pipeline, PipelineConfig

    scan = cast([(CAR_LO, CAR_HI)])

    def pipeline(weight: float, filter_backend: str) -> Pipeline:
        return Pipeline(PipelineConfig(backend="input", min_points=5,
                                       filter=FilterConfig(w_mismatch=weight, filter_backend=filter_backend, trees="")))

    off = pipeline(0.0, "mirror")
    assert off.filter_completer is None  # nothing loaded for a term that does not count
    result = off.process(scan, BOX)
    assert not np.isfinite(result.mismatch[0]) and not np.isfinite(result.filter_terms.get("mismatch", [np.nan])[0])

    on = pipeline(1.5, "mirror")
    assert type(on.completer) is InputCompleter and type(on.filter_completer) is MirrorCompleter
    seen = []
    complete = on.filter_completer.complete
    on.filter_completer.complete = lambda crops, *a, **k: seen.append((crops, complete(crops, *a, **k))) or seen[-1][1]
    result = on.process(scan, BOX)
    assert len(seen) == 1 and len(seen[0][0]) == 1  # one completion, of the one box
    (crops, shapes), = seen
    assert len(shapes[0]) == 2 * len(crops[0])  # the mirror's: the crop and its reflection
    expected = mismatch_scores(crops, shapes, on.config.filter)
    assert np.isfinite(result.mismatch[0]) and result.mismatch[0] == expected[0]
    assert result.filter_terms["mismatch"][0] == expected[0]

    own = pipeline(1.5, "")  # "": the pipeline's own completions (the input's), no second backend
    assert own.filter_completer is None and np.isfinite(own.process(scan, BOX).mismatch[0])


def _heights(rng: np.random.Generator, dtype, kinds: list[str], size) -> list[np.ndarray]:
    """Runs of ground-like heights for the selection tests, one per kind: random, ties (rounded),
    flat with a few lower returns, sorted, reversed, one value; ``size()`` draws each length."""
    cases = []
    for kind in kinds:
        n = 1 if kind == "one" else size()
        v = rng.normal(-1.7, 0.3, n).astype(dtype)
        if kind == "ties":
            v = np.round(v, 1)
        elif kind == "flat":
            v[:] = dtype(-1.73)
            v[: n // 50] -= 0.5
        elif kind in ("sorted", "reversed"):
            v = np.sort(v)[:: 1 if kind == "sorted" else -1].copy()
        cases.append(v)
    return cases


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_kth_smallest_equals_a_partition(dtype):
    """The ground's quantile selection (in place, on a prefix of a work array) gives the value
    np.partition puts at the rank: random values, ties, flat runs with a few lower returns,
    sorted and reversed runs, one value, every rank of a short run."""
    from pcc_ros.pipeline.evidence_kernels import kth_smallest

    rng = np.random.default_rng(7)
    kinds = ["random", "ties", "flat", "sorted", "reversed", "one"] * 4
    for v in _heights(rng, dtype, kinds, lambda: int(rng.integers(2, 3000))):
        work = np.r_[v, rng.normal(size=7).astype(dtype)]  # a longer work array: only the prefix counts
        for quantile in (0.05, 0.5, 0.0, 1.0):
            k = int(quantile * (len(v) - 1))
            assert kth_smallest(work, len(v), k) == np.partition(v, k)[k], (len(v), quantile)
    short = np.array([3, 1, 2, 2, 5, 0], dtype)
    for k in range(len(short)):
        assert kth_smallest(short.copy(), len(short), k) == np.sort(short)[k]


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_bracketed_selection_equals_a_partition(dtype):
    """The ground's selection through a sampled bracket gives np.partition's value at the rank:
    long runs (and short ones, below the sampling) of random, tied, flat and sorted heights at
    the ground's quantile and others, and runs whose sample lies far from the rest (the bracket
    misses: the full selection runs)."""
    from pcc_ros.pipeline.evidence_kernels import BRACKET_SAMPLES, bracketed_kth

    rng = np.random.default_rng(8)
    kinds = ["random", "ties", "flat", "sorted", "reversed"] * 3
    cases = _heights(rng, dtype, kinds, lambda: int(rng.integers(1100, 9000)))
    cases += _heights(rng, dtype, kinds[:5], lambda: int(rng.integers(2, 4 * BRACKET_SAMPLES)))
    for low in (True, False):  # every sampled value far above (or below) all the others
        v = rng.normal(-1.7, 0.3, 5000).astype(dtype)
        v[:: 5000 // BRACKET_SAMPLES] = dtype(50.0 if low else -50.0)
        cases.append(v)
    for v in cases:
        for quantile in (0.05, 0.5, 0.0, 1.0, 0.97):
            k = int(quantile * (len(v) - 1))
            work, spare = v.copy(), np.empty_like(v)
            assert bracketed_kth(work, len(v), k, spare) == np.partition(v, k)[k], (len(v), quantile)


def test_side_pool_is_made_once_when_first_frames_race(monkeypatch):
    """Two pipelines' first filter frames at once share one second thread (none made and leaked)."""
    import threading
    import time
    from concurrent.futures import ThreadPoolExecutor

    from pcc_ros.pipeline import evidence as ev

    made = []

    class SlowPool(ThreadPoolExecutor):  # widens the window between the check and the assignment
        def __init__(self, *args, **kwargs):
            time.sleep(0.05)
            super().__init__(*args, **kwargs)
            made.append(self)

    monkeypatch.setattr(ev, "_SIDE_POOL", None)
    monkeypatch.setattr(ev, "ThreadPoolExecutor", SlowPool)
    start = threading.Barrier(4)
    got = []

    def first_frame():
        start.wait()
        got.append(ev._side_pool())

    threads = [threading.Thread(target=first_frame) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    try:
        assert len(made) == 1 and all(p is made[0] for p in got)
    finally:
        for pool in made:
            pool.shutdown()


def _kernels():
    from pcc_ros.pipeline import evidence_kernels as k

    return (k.counting_sort, k.ray_keys, k.ray_cells, k.ray_counts, k.cell_runs, k.ground_cells, k.ground_quantiles,
            k.expected_counts)


def test_frames_after_warm_up_compile_nothing_new():
    """``warm_up`` (Pipeline start) compiles every kernel signature a frame uses: later frames with
    other box counts, either scan precision, box arrays strided, Fortran-ordered, read-only or
    unaligned (e.g. over a message buffer), empty scans and boxes without a point add no numba
    signature (each would be a compilation of seconds in a running node)."""
    from pcc_ros.pipeline.evidence import local_ground, warm_up

    warm_up()
    before = [list(kernel.signatures) for kernel in _kernels()]
    rng = np.random.default_rng(11)

    def boxes(n: int, layout: str = "") -> Boxes:
        centre = np.c_[rng.uniform(-40, 40, (n, 2)), rng.uniform(-1.2, -0.6, n)]
        size = np.c_[rng.uniform(3.5, 5, n), rng.uniform(1.6, 2, n), rng.uniform(1.3, 1.8, n)]
        yaw = rng.uniform(-np.pi, np.pi, n)
        if layout == "strided":  # columns of one (n, 7) table
            table = np.c_[centre, size, yaw]
            return Boxes(table[:, :3], table[:, 3:6], table[:, 6])
        if layout == "fortran":
            return Boxes(np.asfortranarray(centre), np.asfortranarray(size), yaw)
        if layout == "readonly":
            for a in (centre, size, yaw):
                a.flags.writeable = False
        if layout == "unaligned":
            raw = bytearray(1 + centre.nbytes)
            centre = np.frombuffer(raw, np.float64, offset=1).reshape(n, 3)
            centre.flags.writeable = True
            centre[:] = np.c_[rng.uniform(-40, 40, (n, 2)), np.full(n, -0.9)]
        return Boxes(centre, size, yaw)

    scan = np.c_[rng.uniform(-45, 45, (30_000, 2)), rng.uniform(-2.5, 1, 30_000), rng.uniform(0, 1, 30_000)]
    cloud = scan.astype(np.float32)
    cloud.flags.writeable = False  # as pointcloud2 hands a scan out
    for points in (cloud, cloud[:, :3], scan, scan.astype(np.float16)):
        for n, layout in ((1, ""), (3, "strided"), (130, ""), (4, "fortran"), (5, "readonly"), (6, "unaligned")):
            for workers in (1, 2):
                evidence(points, boxes(n, layout), workers=workers)
        evidence(points[:0], boxes(3))
        evidence(points, Boxes([[200.0, 0.0, -0.9]], [[4.0, 1.8, 1.5]], [0.0]))  # no point near it
        local_ground(points, boxes(7))
    assert [list(kernel.signatures) for kernel in _kernels()] == before


def test_kernels_compile_without_a_writable_cache(monkeypatch, caplog):
    """No writable cache directory for numba (a read-only install, no writable home): the kernels
    compile without a disk cache (a warning says so) instead of the import failing ("cannot cache
    function ...: no locator available"), which took every filter pipeline down at start."""
    import importlib.util

    from numba.core import caching

    from pcc_ros import jit
    from pcc_ros.pipeline import evidence_kernels

    monkeypatch.setattr(caching.CacheImpl, "_locator_classes", [])  # no place numba may write
    monkeypatch.setattr(jit, "uncached", [])
    spec = importlib.util.spec_from_file_location("pcc_ros.pipeline._kernels_uncached", evidence_kernels.__file__)
    module = importlib.util.module_from_spec(spec)
    with caplog.at_level("WARNING"):
        spec.loader.exec_module(module)
    assert sorted(jit.uncached) == sorted(kernel.__name__ for kernel in _kernels())
    assert ["no writable cache directory" in r.getMessage() for r in caplog.records] == [True]
    key = np.array([2, -1, 0, 2, 1, 0], np.int16)
    start, order = np.zeros(4, np.int64), np.zeros(len(key), np.int64)
    assert module.counting_sort(key, np.array([True, False, True]), start, order) == 4
    assert order[:4].tolist() == [2, 5, 0, 3] and start.tolist() == [0, 2, 2, 4]


def test_second_thread_works_in_the_callers_context(monkeypatch):
    """workers >= 2: the ground and expected-return jobs run on the filter's pool thread in a copy
    of the caller's context, so a line they log is the node's at work (node_at_work), not no node's."""
    from pcc_ros.pipeline import evidence as ev
    from pcc_ros.runtime.node import node_at_work, working_for

    seen = []

    def spied(job):
        def spy(*args, **kwargs):
            seen.append(node_at_work.get())
            return job(*args, **kwargs)

        return spy

    for name in ("_footprint_measures", "_expected_beams"):
        monkeypatch.setattr(ev, name, spied(getattr(ev, name)))
    scan, boxes = _scattered_scene(3)
    node = object()
    with working_for(node):
        evidence(scan, boxes, workers=2)
    assert seen == [node, node]


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_a_return_straight_above_or_below_the_sensor_warns_nothing(dtype):
    """A return at x = y = 0 (z != 0) has a slope z / tiny beyond every box's window: counted by no
    box, and no numpy overflow warning on stderr (the band arithmetic overflowed to inf)."""
    import warnings

    boxes = Boxes([[10.0, 0.0, -0.8]], [[4.0, 1.8, 1.5]], [0.0])
    scan = np.array([[0.0, 0.0, -1.0], [0.0, 0.0, 30.0], [10.0, 0.0, -0.8]], dtype)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ev = evidence(scan, boxes)
    assert ev.n_rays[0] == 1 and ev.n_in[0] == 1
