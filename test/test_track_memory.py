"""Track-level completion: a car's past crops in its box frame, bounded, causal, freed on expiry."""

from __future__ import annotations

import numpy as np
import pytest

from pcc_ros.geometry.canonical import from_canonical, to_canonical
from pcc_ros.pipeline.track_memory import TrackMemory
from pcc_ros.types import Boxes

SECOND = 1_000_000_000


def _boxes(centres, ids, length: float = 4.0, yaw: float = 0.0) -> Boxes:
    n = len(centres)
    return Boxes(np.asarray(centres, float).reshape(n, 3), np.tile([length, 1.8, 1.5], (n, 1)), np.full(n, yaw),
                 np.array(["Car"] * n, dtype=object), np.ones(n), np.array(ids, dtype=object))


def test_a_moving_car_accumulates_in_its_own_box_frame():
    rng = np.random.default_rng(0)
    surface = rng.uniform(-0.5, 0.5, (400, 3)) * [1, 0.45, 0.37]
    memory = TrackMemory(max_age_s=1.0)
    seen = []
    for f in range(4):  # the car drives and turns; each frame sees another quarter of it
        centre, yaw = np.array([10.0 + 1.5 * f, 3.0, -0.8]), 0.1 * f
        part = surface[(np.arange(len(surface)) % 4) == f]
        sensor = from_canonical(part, centre, yaw, 4.0)
        crop = to_canonical(sensor, centre, yaw, 4.0).astype(np.float32)
        boxes = _boxes([centre], ["7"], yaw=yaw)
        out = memory.update(boxes, [crop], f * SECOND // 10)[0]
        np.testing.assert_allclose(out[: len(crop)], crop)  # this frame's crop first
        seen.append(part)
        expected = np.concatenate(seen)
        assert len(out) == len(expected)
        np.testing.assert_allclose(np.sort(out, axis=0), np.sort(expected, axis=0), atol=1e-5)  # same place
    # a longer box of the same id (a detector's size noise): the stored metres keep their size
    out = memory.update(_boxes([[20.0, 3, -0.8]], ["7"], length=5.0), [np.zeros((3, 3), np.float32)],
                        4 * SECOND // 10)[0]
    assert np.abs(out[3:, 0]).max() <= 0.5 * 4.0 / 5.0 + 1e-6


def test_expiry_frees_tracks_and_old_frames_and_time_going_back_clears():
    memory = TrackMemory(max_age_s=0.5)
    crop = np.zeros((5, 3), np.float32)
    memory.update(_boxes([[5, 0, 0], [9, 0, 0]], ["a", "b"]), [crop, crop], 0)
    memory.update(_boxes([[5, 0, 0]], ["a"]), [crop], 3 * SECOND // 10)
    assert len(memory) == 2
    out = memory.update(_boxes([[5, 0, 0]], ["a"]), [crop], 7 * SECOND // 10)  # b unseen 0.7 s: freed
    assert set(memory.tracks) == {"id:a"}
    assert len(out[0]) == 5 + 5  # the frame at 0 s expired, the one at 0.3 s is kept
    memory.update(_boxes([[5, 0, 0]], ["a"]), [crop], 0)  # a bag looped
    assert memory.update(_boxes([[5, 0, 0]], ["a"]), [crop], 1)[0].shape == (10, 3)
    with pytest.raises(ValueError):
        memory.update(_boxes([[5, 0, 0]], ["a"]), [], 2)


def test_bounded_under_a_stream_of_new_ids():
    memory = TrackMemory(max_age_s=60.0, max_tracks=16, max_points=300, max_frames=5)
    rng = np.random.default_rng(1)
    for f in range(200):  # every frame 8 cars never seen before, each with a large crop
        ids = [f"{f}-{k}" for k in range(8)]
        crops = [rng.normal(size=(500, 3)).astype(np.float32) * 0.1 for _ in ids]
        memory.update(_boxes(rng.uniform(-30, 30, (8, 3)), ids), crops, f * SECOND // 10)
        assert len(memory) <= 16
        assert all(t.points() <= 300 for t in memory.tracks.values())
    assert memory.stored_points <= 16 * 300
    # one id over many frames: at most max_frames frames and max_points points
    for f in range(200, 230):
        memory.update(_boxes([[0, 0, 0]], ["same"]), [rng.normal(size=(100, 3)).astype(np.float32)], f * SECOND // 10)
    track = memory.tracks["id:same"]
    assert len(track.frames) <= 5 and track.points() <= 300


def test_without_ids_the_nearest_box_within_the_gate_is_the_same_car():
    memory = TrackMemory(gate_m=2.0)
    crop = np.zeros((4, 3), np.float32)
    memory.update(_boxes([[10, 0, 0], [10, 6, 0]], ["", ""]), [crop, crop], 0)
    # both cars moved 1 m; a third appears far away; one box carries an id (its own track)
    out = memory.update(_boxes([[11, 6, 0], [11, 0, 0], [40, 0, 0], [10, 3, 0]], ["", "", "", "x"]),
                        [crop, crop, crop, crop], SECOND // 10)
    assert [len(o) for o in out] == [8, 8, 4, 4]
    assert sorted(memory.tracks) == ["auto:0", "auto:1", "auto:2", "id:x"]
    np.testing.assert_allclose(memory.tracks["auto:0"].centre, [11, 0, 0])  # followed, not swapped


def test_pipeline_completes_from_the_accumulated_crops():
    from pcc_ros.pipeline.core import Pipeline, PipelineConfig

    rng = np.random.default_rng(2)
    centre = np.array([8.0, 2.0, -0.9])
    single = Pipeline(PipelineConfig(backend="input", min_points=10))
    tracked = Pipeline(PipelineConfig(backend="input", min_points=10, track_memory=True))
    counts = []
    for f in range(3):
        car = from_canonical(rng.uniform(-0.45, 0.45, (60, 3)) * [1, 0.4, 0.3], centre, 0.0, 4.4)
        boxes = Boxes(centre[None], np.array([[4.4, 1.8, 1.5]]), np.zeros(1), np.array(["Car"], dtype=object),
                      np.ones(1), np.array(["3"], dtype=object))
        a = single.process(car.astype(np.float32), boxes, f * SECOND // 10)
        b = tracked.process(car.astype(np.float32), boxes, f * SECOND // 10)
        assert len(a.completions[0]) == 60
        counts.append(len(b.completions[0]))
        assert "track_memory_ms" in b.timings_ms and len(b.crops[0]) == 60  # the filter reads this frame's crop
    assert counts == [60, 120, 180]


def test_real_evaluation_feeds_the_frames_in_order_and_causally():
    from pcc_ros.errors import ConfigError
    from pcc_ros.workflows.evaluate_real import track_memory_inputs

    def inst(frame: int, track: str, x: float, n: int) -> dict:
        return {"frame_key": f"src:0000:{frame}", "frame": frame, "track": track, "center": np.array([x, 0.0, 0.0]),
                "size": np.array([4.0, 1.8, 1.5]), "yaw": 0.0, "label": "Car",
                "partial": np.full((n, 3), frame / 100, np.float32)}

    # given out of order: frame 2 first; two cars 10 m apart
    instances = [inst(2, "a", 10.5, 3), inst(0, "a", 10.0, 1), inst(1, "a", 10.2, 2), inst(1, "b", 20.0, 5)]
    for association in ("ids", "nearest"):
        clouds, ms = track_memory_inputs(instances, association)
        assert [len(c) for c in clouds] == [3 + 1 + 2, 1, 2 + 1, 5] and ms >= 0
        np.testing.assert_allclose(clouds[0][:3], instances[0]["partial"])  # this frame's crop first
    with pytest.raises(ConfigError):
        track_memory_inputs(instances, "tracker")
