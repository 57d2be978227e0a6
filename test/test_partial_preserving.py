"""Partial-preserving completion (``keep_input``) and the box-aspect frame (``sizes`` /
``box_aspect``), shared by every backend through ``Completer.complete``, and what the pipeline
and the real-data evaluation make of them."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pcc_ros.errors import CheckpointError, ConfigError, DataError
from pcc_ros.models.base import ASPECT_SCALE_RANGE, Completer, aspect_scales, median_box_aspect
from pcc_ros.models.registry import create, load_completer
from pcc_ros.types import Boxes


class UnitBody(Completer):
    """Returns a fixed body filling the reference box (aspect 0.41, 0.375) and records its inputs."""

    def __init__(self):
        super().__init__()
        self.seen: list[np.ndarray] = []
        grid = np.stack(np.meshgrid(*[np.linspace(-1, 1, 5)] * 3), -1).reshape(-1, 3)
        self.body = (grid * [0.5, 0.205, 0.1875]).astype(np.float32)

    def _complete(self, clouds, contexts):
        self.seen.extend(c.copy() for c in clouds)
        return [self.body.copy() for _ in clouds]


def _partials(seed=0):
    rng = np.random.default_rng(seed)
    return [rng.uniform(-0.3, 0.3, (n, 3)).astype(np.float32) for n in (7, 40)]


def test_keep_input_puts_the_partial_first_then_the_generated_points():
    backend = UnitBody()
    partials = _partials()
    plain = backend.complete(partials)
    kept = backend.complete(partials, keep_input=True)
    for p, g, k in zip(partials, plain, kept):
        assert len(k) == len(p) + len(g)
        np.testing.assert_array_equal(k[: len(p)], p)
        np.testing.assert_array_equal(k[len(p) :], g)
        assert k.dtype == np.float32


def test_keep_input_adds_nothing_to_outputs_that_hold_the_input():
    partials = _partials()
    for name in ("input", "mirror"):
        backend = load_completer(name)
        assert backend.contains_input
        for a, b in zip(backend.complete(partials), backend.complete(partials, keep_input=True)):
            np.testing.assert_array_equal(a, b)


def test_box_aspect_frame_is_applied_and_inverted_exactly():
    backend = UnitBody()
    partials = _partials()
    sizes = np.array([[4.4, 1.8, 2.0], [4.0, 1.64, 1.5]])  # a tall van, a car of the reference aspect
    backend.box_aspect = (0.41, 0.375)
    out = backend.complete(partials, sizes=sizes)
    scales = aspect_scales(sizes, backend.box_aspect, 2)
    np.testing.assert_allclose(scales[1], [1.0, 1.0, 1.0], atol=1e-6)
    assert scales[0, 2] == pytest.approx(0.375 / (2.0 / 4.4))  # the van is squeezed into the reference box
    for p, seen, s in zip(partials, backend.seen, scales):
        np.testing.assert_allclose(seen, p * s, rtol=1e-6)  # the network saw the scaled crop
    # ... and its body comes back stretched to the van's own height: top at h / (2 l)
    assert out[0][:, 2].max() == pytest.approx(0.1875 / scales[0, 2], rel=1e-5)
    assert out[0][:, 2].max() * 4.4 == pytest.approx(1.0, rel=1e-5)
    assert out[0][:, 2].max() > out[1][:, 2].max()
    # without sizes (or without an aspect) nothing is scaled
    backend.seen.clear()
    backend.complete(partials)
    np.testing.assert_array_equal(backend.seen[0], partials[0])
    backend.box_aspect = None
    backend.seen.clear()
    backend.complete(partials, sizes=sizes)
    np.testing.assert_array_equal(backend.seen[0], partials[0])


def test_aspect_scales_are_clipped_and_checked():
    scales = aspect_scales(np.array([[1.0, 3.0, 0.05]]), (0.4, 0.37), 1)
    assert scales.min() >= ASPECT_SCALE_RANGE[0] and scales.max() <= ASPECT_SCALE_RANGE[1]
    with pytest.raises(DataError, match="sizes"):
        aspect_scales(np.ones((2, 3)), (0.4, 0.37), 3)
    with pytest.raises(DataError, match="positive"):
        aspect_scales(np.array([[4.0, 0.0, 1.5]]), (0.4, 0.37), 1)
    backend = UnitBody()
    backend.box_aspect = (0.4, 0.37)
    with pytest.raises(DataError):
        backend.complete(_partials(), sizes=np.array([[4.0, 1.8, np.nan], [4.0, 1.8, 1.5]]))
    assert median_box_aspect(np.array([[4.0, 2.0, 1.0], [2.0, 1.0, 1.0], [5.0, 2.0, 2.0]])) == pytest.approx((0.5, 0.4))


def test_box_aspect_is_saved_loaded_and_refused_when_malformed(tmp_path):
    from pcc_ros.models.checkpoint import load_config, set_box_aspect

    net = create("pointpncnet", device="cpu", box_aspect=(0.41, 0.38))
    path = net.save(tmp_path / "pnc.safetensors")
    assert load_config(path)["box_aspect"] == {"width_over_length": 0.41, "height_over_length": 0.38}
    assert load_completer("pointpncnet", path, device="cpu").box_aspect == (0.41, 0.38)
    assert load_completer("pointpncnet", path, device="cpu", box_aspect=(0.5, 0.5)).box_aspect == (0.5, 0.5)
    plain = create("pointpncnet", device="cpu").save(tmp_path / "plain.safetensors")
    assert "box_aspect" not in load_config(plain)
    assert load_completer("pointpncnet", plain, device="cpu").box_aspect is None
    set_box_aspect(plain, (0.4, 0.36), "median of a test set")
    assert load_config(plain)["box_aspect"]["source"] == "median of a test set"
    assert load_completer("pointpncnet", plain, device="cpu").box_aspect == (0.4, 0.36)
    config_path = plain.with_suffix(".json")
    config = json.loads(config_path.read_text())
    config["box_aspect"] = {"width_over_length": "wide"}
    config_path.write_text(json.dumps(config))
    with pytest.raises(CheckpointError, match="box_aspect"):
        load_completer("pointpncnet", plain, device="cpu")
    with pytest.raises(ConfigError):
        create("pointpncnet", device="cpu", box_aspect=(0.4, -1.0))


def test_shipped_learned_backends_record_their_box_aspect():
    for name in ("pointpncnet", "trapcc"):
        aspect = load_completer(name, device="cpu").box_aspect
        assert aspect is not None and 0.3 < aspect[0] < 0.5 and 0.3 < aspect[1] < 0.45


def test_pipeline_publishes_the_partial_preserving_completion_by_default():
    from pcc_ros.geometry.canonical import from_canonical
    from pcc_ros.pipeline.core import SOURCE_COMPLETED, SOURCE_OBSERVED, Pipeline, PipelineConfig
    from pcc_ros.pipeline.filter import FilterConfig

    rng = np.random.default_rng(3)
    boxes = Boxes(center=[[12.0, 2.0, -0.7]], size=[[4.4, 1.8, 2.0]], yaw=[0.4], label=["Van"], score=[0.9],
                  track_id=["1"])
    local = rng.uniform(-1, 1, (300, 3)) * [2.1, 0.85, 0.9]
    local[:, 1] = -0.85  # one flank
    c, s = np.cos(0.4), np.sin(0.4)
    points = (local @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T + boxes.center[0]).astype(np.float32)
    config = PipelineConfig(backend="input", min_points=10, filter=FilterConfig(rule="trapcc"))
    assert config.include_observed_points  # the default
    backend = UnitBody()
    backend.box_aspect = (0.41, 0.375)
    result = Pipeline(config, completer=backend).process(points, boxes)
    observed = result.completed_source == SOURCE_OBSERVED
    assert observed.sum() == len(result.crops[0]) and (result.completed_source == SOURCE_COMPLETED).sum() == 125
    # the published car equals Completer.complete(keep_input=True), moved into the sensor frame
    union = backend.complete(result.crops, sizes=boxes.size, keep_input=True)[0]
    expected = from_canonical(union, boxes.center[0], float(boxes.yaw[0]), float(boxes.size[0, 0]))
    published = np.concatenate([result.completed_points[~observed], result.completed_points[observed]])
    reordered = np.concatenate([expected[len(result.crops[0]) :], expected[: len(result.crops[0])]])
    np.testing.assert_allclose(published, reordered, atol=1e-4)
    # the generated points were made in the aspect frame with the detection's size
    assert result.completion_points(0)[:, 2].max() == pytest.approx(boxes.center[0, 2] + 1.0, abs=1e-3)


def _frames_with_a_shifted_detection():
    """Three frames of one labelled car; the detector's box is 0.3 m off and 10 % longer."""
    from pcc_ros.geometry.canonical import from_canonical
    from pcc_ros.types import Sample

    rng = np.random.default_rng(5)
    size = np.array([4.0, 1.8, 1.5])
    frames = []
    for k in range(3):
        center = np.array([10.0 + 3 * k, 4.0, -0.8])
        surface = rng.uniform(-1, 1, (500, 3)) * (size / size[0] / 2 * 0.95)
        surface[:, 1] = -0.95 * size[1] / size[0] / 2
        sensor = from_canonical(surface, center, 0.2, size[0]).astype(np.float32)
        gt = Boxes(center=[center], size=[size], yaw=[0.2], label=["Car"], score=[1.0], track_id=["7"])
        det = Boxes(center=[[center[0] + 0.3, center[1], center[2]], [40.0, -10.0, -0.8]],
                    size=[size * [1.1, 1.0, 1.0], size], yaw=[0.2, 0.0], label=["Car", "Car"], score=[2.0, 1.0])
        frames.append(Sample(stamp_ns=k, frame_id="velodyne", points=sensor, ground_truth=gt, detections=det,
                            sequence="s", index=k))
    return frames


def test_real_instances_from_detections_move_the_reference_into_the_detection_frame(monkeypatch, tmp_path):
    import pcc_ros.workflows.evaluate_real as evaluate_real
    from pcc_ros.geometry.canonical import from_canonical

    frames = _frames_with_a_shifted_detection()
    monkeypatch.setattr(evaluate_real, "open_frames", lambda path, **kw: iter(frames))
    gt_inst, _ = evaluate_real.real_instances([tmp_path], min_points=10)
    det_inst, report = evaluate_real.real_instances([tmp_path], min_points=10, boxes="detections",
                                                    detections_dir=tmp_path)
    assert len(gt_inst) == len(det_inst) == 3
    assert report[str(tmp_path)]["skipped"]["detection_unmatched"] == 3  # the box at 40 m holds no car
    g, d = gt_inst[0], det_inst[0]
    assert d["size"][0] == pytest.approx(4.4)
    # the same reference points, each expressed in its own box's canonical frame
    a = from_canonical(g["reference"], g["center"], g["yaw"], g["size"][0])
    b = from_canonical(d["reference"], d["center"], d["yaw"], d["size"][0])
    np.testing.assert_allclose(a, b, atol=1e-4)
    assert not np.allclose(g["reference"][:, 0], d["reference"][:, 0], atol=0.01)


@pytest.mark.slow
def test_eval_real_rows_are_the_published_output_and_the_generated_points(shared_data, tmp_path, capsys):
    from pcc_ros.cli.main import main

    out = tmp_path / "real.json"
    rc = main(["eval", "--real", "--real-sources", str(shared_data / "kitti_tracking"), "--backends",
               "mirror,pointpncnet", "--json", str(out)])
    assert rc == 0
    result = json.loads(out.read_text())
    rows = result["backends"]
    published, generated = rows["pointpncnet"]["overall"], rows["pointpncnet/generated"]["overall"]
    assert published["fidelity"] == 0.0  # every observed point is in the published cloud
    assert generated["fidelity"] > 0.0
    assert published["points_min"] > generated["points_min"]
    assert published["completeness"] < generated["completeness"]
    assert rows["pointpncnet"]["box_aspect"] is not None
    assert result["input_crop"] == {"box_margin": 0.1, "ground_margin": 0.05}
    assert "pointpncnet/generated" in capsys.readouterr().out


def test_denser_decoding_keeps_the_trained_points_and_adds_points_between_them():
    rng = np.random.default_rng(4)
    clouds = [rng.normal(size=(300, 3)).astype(np.float32) * [0.4, 0.15, 0.12]]
    plain = create("pointpncnet", device="cpu")
    dense = create("pointpncnet", device="cpu", decode_density=2)
    dense.model.load_state_dict(plain.model.state_dict())
    a, b = plain.complete(clouds)[0], dense.complete(clouds)[0]
    assert len(a) == 2048 and len(b) == 2048 * 9 // 4  # 2x2 folding grids become 3x3
    from scipy.spatial import cKDTree

    assert cKDTree(b).query(a)[0].max() < 1e-5  # every trained grid point is still decoded
    assert dense.decode_density == 2
    with pytest.raises(ConfigError, match="decode_density"):
        create("pointpncnet", device="cpu", decode_density=0)
    from pcc_ros.pipeline.core import PipelineConfig

    assert PipelineConfig().decode_density == 2
    with pytest.raises(ConfigError, match="decode_density"):
        PipelineConfig(decode_density=9)
