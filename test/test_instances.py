"""Instance extraction, the cache format, training views, track aggregation and the evenness test."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pcc_ros.data.gt_pools import PoolConfig, build_pools, candidate_score
from pcc_ros.data.instance_cache import EvalShapes, InstanceCache, multiview_groups
from pcc_ros.data.instances import ExtractConfig, extract_instances
from pcc_ros.data.track_aggregate import aggregate_instances
from pcc_ros.errors import DataError
from pcc_ros.geometry.canonical import from_canonical, to_canonical
from pcc_ros.types import Boxes, Sample

CAR = np.array([4.0, 1.8, 1.5])


def car_surface(n: int, rng: np.random.Generator) -> np.ndarray:
    """Canonical surface samples of an ellipsoidal car body (length 0.95 in canonical units)."""
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d * (CAR / CAR[0] / 2.0 * 0.95)


def visible(surface: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """Surface points facing the sensor (outward normal toward it): self-occlusion."""
    normal = surface / (CAR / CAR[0] / 2.0 * 0.95) ** 2
    return np.einsum("ij,ij->i", normal, origin - surface) > 0


def make_track_frames(n_frames=24, noise=0.005, seed=0, sequence="0000", track="7", with_pose=False):
    """A car driving past the sensor (moving + turning), seen from changing angles."""
    rng = np.random.default_rng(seed)
    surface = car_surface(20000, rng)
    frames = []
    for f in range(n_frames):
        center = np.array([-15.0 + 1.3 * f, 6.0, -0.9])
        yaw = 0.02 * f
        origin_c = to_canonical(np.zeros((1, 3)), center, yaw, CAR[0])[0]
        pts_c = surface[visible(surface, origin_c)]
        pts_c = pts_c[rng.random(len(pts_c)) < 0.15]
        pts_c = pts_c + rng.normal(0, noise, pts_c.shape)
        car = from_canonical(pts_c, center, yaw, CAR[0])
        ground = np.c_[rng.uniform(-30, 30, (3000, 2)), np.full(3000, -1.65)]
        pts = np.c_[np.r_[car, ground], rng.uniform(0, 1, len(car) + len(ground))].astype(np.float32)
        boxes = Boxes([center, [30.0, -30.0, 0.0], [np.nan, 0, 0]], [CAR, CAR, CAR], [yaw, 0.0, 0.0],
                      label=["Car", "Car", "Car"], track_id=[track, "99", "98"])
        pose = None
        if with_pose:
            pose = np.eye(4)
            pose[0, 3] = 2.0 * f
        frames.append(Sample(stamp_ns=f * 100_000_000, frame_id="velodyne", points=pts, ground_truth=boxes,
                            sequence=sequence, index=f, pose=pose))
    return frames, surface


def nn_dist(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    from scipy.spatial import cKDTree

    return cKDTree(b).query(a)[0]


@pytest.fixture
def track_cache(tmp_path):
    frames, surface = make_track_frames()
    cache = extract_instances(frames, tmp_path / "cache", ExtractConfig(ground_margin=0.1), progress=False)
    return cache, surface, frames


def test_extraction_records(track_cache):
    cache, _, frames = track_cache
    # One car per frame: the far box has no points (min_points), the NaN box is counted.
    assert len(cache) == len(frames)
    assert cache.index["skipped"] == {"invalid_box": len(frames), "too_few_points": len(frames)}
    i = 5
    pts = cache.points(i)
    assert pts.dtype == np.float32 and pts.shape[1] == 3 and len(pts) == cache.meta["num_points"][i]
    assert np.abs(pts).max() < 0.6  # canonical: scaled by 1 / length
    frame = frames[i]
    box = frame.ground_truth[0]
    np.testing.assert_allclose(cache.meta["box_center"][i], box.center[0])
    np.testing.assert_allclose(cache.meta["distance"][i], np.linalg.norm(box.center[0]), rtol=1e-6)
    np.testing.assert_allclose(cache.meta["origin"][i], to_canonical(np.zeros((1, 3)), box.center[0], box.yaw[0],
                                                                      4.0)[0], atol=1e-5)
    # Points map back into the scan exactly (ground returns under the car were dropped).
    back = from_canonical(pts, box.center[0], box.yaw[0], 4.0)
    assert nn_dist(back, frame.xyz.astype(np.float64)).max() < 1e-4
    assert (back[:, 2] >= box.center[0, 2] - 0.75 + 0.1 - 1e-5).all()
    assert set(cache.meta["track"]) == {"7"} and set(cache.meta["sequence"]) == {"0000"}
    assert len(set(cache.meta["split"])) == 1  # split by track: one track, one split
    assert not cache.meta["has_shape"].any()
    assert np.isnan(cache.meta["pose"]).all()


def test_cache_is_idempotent_resumable_and_guarded(tmp_path):
    frames, _ = make_track_frames(n_frames=10)
    out = tmp_path / "c"
    cfg = ExtractConfig(shard_points=1500)  # several shards
    full = extract_instances(frames, out, cfg, progress=False)
    assert len(full.index["shards"]) > 1
    stamp = (out / "index.json").stat().st_mtime_ns
    again = extract_instances(frames, out, cfg, progress=False)  # nothing to do
    assert (out / "index.json").stat().st_mtime_ns == stamp and len(again) == len(full)

    # An interrupted run resumes after the frames it had stored.
    out2 = tmp_path / "c2"

    def interrupted():
        for k, f in enumerate(frames):
            if k == 7:
                raise KeyboardInterrupt
            yield f

    with pytest.raises(KeyboardInterrupt):
        extract_instances(interrupted(), out2, cfg, progress=False)
    partial = json.loads((out2 / "index.json").read_text())
    assert not partial["complete"] and 0 < partial["frames_done"] < 7
    with pytest.raises(DataError, match="did not finish"):
        InstanceCache.load(out2)
    resumed = extract_instances(frames, out2, cfg, progress=False)
    assert len(resumed) == len(full)
    for i in range(len(full)):
        np.testing.assert_array_equal(resumed.points(i), full.points(i))
    np.testing.assert_array_equal(resumed.meta["frame"], full.meta["frame"])

    # Other options: refused without --force, rebuilt with it.
    other = ExtractConfig(min_points=50, shard_points=1500)
    with pytest.raises(DataError, match="--force"):
        extract_instances(frames, out, other, progress=False)
    rebuilt = extract_instances(frames, out, other, force=True, progress=False)
    assert (rebuilt.meta["num_points"] >= 50).all()
    # A foreign non-empty directory is never overwritten.
    (tmp_path / "foreign").mkdir()
    (tmp_path / "foreign" / "x.txt").write_text("mine")
    with pytest.raises(DataError, match="not an instance cache"):
        extract_instances(frames, tmp_path / "foreign", cfg, progress=False)


def test_corrupt_cache_is_reported(track_cache):
    cache, _, _ = track_cache
    offsets = cache.root / "shards" / "00000.offsets.npy"
    np.save(offsets, np.array([0, 5], dtype=np.int64))
    with pytest.raises(DataError, match="inconsistent"):
        InstanceCache.load(cache.root)
    (cache.root / "shards" / "00000.points.npy").write_bytes(b"garbage")
    with pytest.raises(DataError, match="unreadable"):
        InstanceCache.load(cache.root)
    with pytest.raises(DataError, match=r"index\.json"):
        InstanceCache.load(cache.root / "nowhere")


def test_aggregation_of_consistent_track_lands_on_true_surface(track_cache):
    cache, surface, _ = track_cache
    (obs,) = cache.tracks().values()
    merged = aggregate_instances(cache, obs)
    assert len(merged) == cache.meta["num_points"].sum()
    noise = 0.005
    d = nn_dist(merged.astype(np.float64), surface)
    assert np.median(d) < 2 * noise and np.percentile(d, 95) < 4 * noise
    # Several views together cover far more of the car than the best single view.
    cover = lambda cloud: (nn_dist(surface, cloud.astype(np.float64)) < 0.03).mean()  # noqa: E731
    best_single = max(cover(cache.points(i)) for i in obs)
    assert cover(merged) > best_single + 0.15


def test_multiview_groups(tmp_path):
    frames, _ = make_track_frames(n_frames=43)
    cache = extract_instances(frames, tmp_path / "m", progress=False)
    groups = multiview_groups(cache, group_size=20, min_views=4)
    assert [len(g) for g in groups] == [20, 23]  # a 3-observation tail joins the previous run
    for g in groups:
        assert (np.diff(cache.meta["frame"][g]) == 1).all()  # sequential observations
    assert [len(g) for g in cache.multiview_groups(group_size=20, min_views=4)] == [20, 23]


def test_detections_without_ids_group_by_their_matched_track(tmp_path):
    """A detector gives no track ids: the training views group by the matched labelled track (a
    tracker's association); evaluation's own track keys stay the detections' (none)."""
    frames, _ = make_track_frames(n_frames=24)
    for frame in frames:  # the detector finds the car (its box a little off) and nothing else
        gt = frame.ground_truth
        frame.detections = Boxes(gt.center[:1] + np.array([0.1, 0.0, 0.0]), gt.size[:1], gt.yaw[:1], label=["Car"],
                                 track_id=[""], score=[0.9])
    cache = extract_instances(frames, tmp_path / "det", ExtractConfig(boxes="detections"), progress=False)
    assert (cache.meta["track"] == "").all() and (cache.meta["gt_track"] == "7").all()
    assert all("/#" in k for k in cache.track_keys())  # unchanged: no ids of their own
    assert [len(g) for g in cache.multiview_groups(group_size=20, min_views=4)] == [20, 4]


def test_evenness_and_pools(tmp_path):
    rng = np.random.default_rng(1)
    whole = car_surface(5000, rng)
    one_side = whole[whole[:, 1] < 0]
    assert candidate_score(whole, 0.02)[0] > 0.6
    score, ev = candidate_score(one_side, 0.02)
    assert score == 0.0 and ev["top"] == 0.0 and ev["front"] == 0.0 and ev["side"] > 0.6

    frames, _ = make_track_frames(n_frames=24)  # a drive-by: sees front, side and back
    seen_one_side, _ = make_track_frames(n_frames=3, sequence="0002", track="3")
    cache = extract_instances(frames + seen_one_side, tmp_path / "g", progress=False)
    pools = build_pools([cache], split=None, config=PoolConfig(min_points=1024, min_half_points=200))
    assert pools.stats["whole"]["candidates"] == 2  # both tracks have enough points ...
    assert pools.whole.key.tolist() == ["0:0000/7"]  # ... only the drive-by is even (Otsu cut)
    assert pools.stats["whole"]["admitted"] == 1 and pools.whole.count[0] > 0
    assert "0:0000/7" in pools.front.key.tolist() and "0:0000/7" in pools.back.key.tolist()
    front = pools.front.cloud(pools.front.key.tolist().index("0:0000/7"))
    assert (front[:, 0] >= 0).all()


def test_synthcars_shapes_are_eval_only(tmp_path):
    root = tmp_path / "synth"
    (root / "shapes" / "0000").mkdir(parents=True)
    shape = car_surface(16384, np.random.default_rng(0)).astype(np.float32)
    np.save(root / "shapes" / "0000" / "7.npy", shape)
    (root / "meta.json").write_text(json.dumps({"splits": {"train": ["0001"], "test": ["0000"]}}))
    frames, _ = make_track_frames(n_frames=4)
    cache = extract_instances(frames, tmp_path / "s", source=None, synthcars=root, progress=False)
    assert cache.meta["has_shape"].all()
    assert set(cache.meta["split"]) == {"test"}  # the SynthCars test sequence
    assert not hasattr(cache, "shape") and "shape" not in cache.meta
    shapes = EvalShapes.load(cache.root)
    np.testing.assert_array_equal(shapes.for_instance(cache, 0), shape)
    assert shapes.get("0000", "99") is None


def test_splits_are_deterministic_by_track(tmp_path):
    frames = []
    for t in range(40):
        f, _ = make_track_frames(n_frames=2, sequence=f"{t % 3:04d}", track=str(t), seed=t)
        frames += f
    a = extract_instances(frames, tmp_path / "a", progress=False)
    b = extract_instances(frames, tmp_path / "b", progress=False)
    np.testing.assert_array_equal(a.meta["split"], b.meta["split"])
    for obs in a.tracks().values():
        assert len(set(a.meta["split"][obs])) == 1
    assert set(a.meta["split"]) == {"train", "val", "test"}
    assert len(a.indices("train")) > len(a.indices("test")) > 0
    info = a.info()
    assert info["tracks"] == 40 and info["observations_per_track"]["min"] == 2
    assert sum(len(g) for g in a.frame_groups()) == len(a)


def test_real_kitti_tracking_produces_car_tracks(shared_data, tmp_path):
    from pcc_ros.data.sources import open_frames

    src = shared_data / "kitti_tracking"
    cache = extract_instances(open_frames(src), tmp_path / "k", source=src, progress=False)
    tracks = cache.tracks()
    assert len(tracks) >= 2
    assert all(len(obs) >= 10 for obs in tracks.values())  # several observations each
    assert set(cache.meta["label"]) <= {"Car", "Van"}
    assert (cache.meta["num_points"] >= 10).all()
    for i in range(len(cache)):
        assert np.abs(cache.points(i)).max() <= 0.75  # inside the box, canonical units
    (tracks_obs,) = [v for v in tracks.values() if len(v) == max(len(x) for x in tracks.values())]
    merged = aggregate_instances(cache, tracks_obs)
    assert len(merged) > 3 * np.median(cache.meta["num_points"][tracks_obs])


def test_extract_node_crop_crops_as_completion_node(shared_data, tmp_path):
    """`pcc extract --node-crop`: training inputs cropped with the node's box_margin / ground_margin
    (the pipeline defaults), i.e. the same points the node completes."""
    from pcc_ros.cli.main import main
    from pcc_ros.data.sources import open_frames
    from pcc_ros.geometry.boxes import crop_canonical
    from pcc_ros.pipeline.config import PipelineConfig
    from pcc_ros.types import class_mask

    src = shared_data / "kitti_object"
    assert main(["extract", str(src), "--out", str(tmp_path / "node"), "--node-crop", "--no-progress"]) == 0
    assert main(["extract", str(src), "--out", str(tmp_path / "tight"), "--no-progress"]) == 0
    node, tight = InstanceCache.load(tmp_path / "node"), InstanceCache.load(tmp_path / "tight")
    cfg = PipelineConfig()
    assert (node.index["config"]["margin"], node.index["config"]["ground_margin"]) == (cfg.box_margin,
                                                                                       cfg.ground_margin)
    assert tight.index["config"]["margin"] == 0.0
    assert node.meta["num_points"].sum() > tight.meta["num_points"].sum()  # the margins hold more points
    first_frame = node.meta["frame"][0]
    frame = next(f for f in open_frames(src) if f.index == first_frame)
    gt = frame.ground_truth[class_mask(frame.ground_truth.label, ("Car", "Van"))]
    _, crops = crop_canonical(np.asarray(frame.points), gt, cfg.box_margin, cfg.ground_margin)
    first = [len(c) for c in crops if len(c) >= 10]
    assert first and sorted(node.meta["num_points"][node.meta["frame"] == first_frame].tolist()) == sorted(first)


def test_label_planes_place_the_matched_labelled_box_in_a_detector_crop(tmp_path):
    """A detector's box 0.3 m to the car's left and turned 0.05 rad: each crop records where the
    matched labelled box's centre and heading lie in its frame (read from the source's labels);
    a labelled-box cache's plane is its own box's."""
    from pcc_ros.data.synthetic import writer

    frames, _ = make_track_frames(n_frames=3)
    calib = writer.calibration()
    lines = []
    for frame in frames:
        gt = frame.ground_truth[:1]
        c, s = np.cos(gt.yaw[0]), np.sin(gt.yaw[0])
        frame.detections = Boxes(gt.center + 0.3 * np.array([-s, c, 0.0]), gt.size, gt.yaw + 0.05, label=["Car"],
                                 track_id=[""], score=[0.9])
        lines += writer.tracking_label_lines(gt, frame.index, np.zeros(1), calib)
    src = tmp_path / "src" / "training"
    writer.write_text(src / "label_02" / "0000.txt", lines)
    (src / "calib").mkdir()
    calib.write(src / "calib" / "0000.txt")
    det = extract_instances(frames, tmp_path / "det", ExtractConfig(boxes="detections"), source=tmp_path / "src",
                            progress=False)
    planes = det.label_planes()
    for i in range(len(det)):
        box = frames[int(det.meta["frame"][i])].detections
        want = to_canonical(frames[int(det.meta["frame"][i])].ground_truth.center[:1], box.center[0], box.yaw[0],
                            box.size[0, 0])[0]
        assert planes[i, :2] == pytest.approx(want[:2], abs=2e-3)  # labels are written to 0.01 m
        assert abs(want[1]) * CAR[0] == pytest.approx(0.3, abs=0.01)
        assert planes[i, 2] == pytest.approx(-0.05, abs=0.01)
    tight = extract_instances(frames, tmp_path / "gt", ExtractConfig(), progress=False)
    assert (tight.label_planes() == 0).all()
    # PointPnCNet's mirror_plane=label: the detector crops' views carry their car plane's reflection
    from pcc_ros.models.pointpncnet import PlaneView, training_recipe

    groups = training_recipe("default", mirror_plane="label").training_data(det, None, min_points=1)
    views = [v for g in groups for v in g]
    assert views and all(isinstance(v, PlaneView) for v in views)
    plain = training_recipe("default", mirror_plane="label").training_data(tight, None, min_points=1)
    assert not any(isinstance(v, PlaneView) for g in plain for v in g)
