"""SynthCars: geometry of the simulated scans, file layout, round trips, determinism."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

from pcc_ros.data.kitti import KittiTracking
from pcc_ros.data.kitti_format import Calibration, camera_to_lidar_boxes, parse_label_lines
from pcc_ros.data.synthetic import generate, load_shape
from pcc_ros.data.synthetic.detector import FALSE_KINDS, KINDS, DetectorParams, detect
from pcc_ros.data.synthetic.furniture import BUILDERS
from pcc_ros.data.synthetic.generator import SPLIT_CODES, build_sequence, seeded_rng, sensor_pose, simulate_frame
from pcc_ros.data.synthetic.lidar import Sensor, build_scene, cast
from pcc_ros.data.synthetic.mesh import is_closed_oriented
from pcc_ros.data.synthetic.scene import KIND_VEHICLE
from pcc_ros.data.synthetic.vehicles import FAMILIES, build_vehicle, canonical_shape
from pcc_ros.data.synthetic.writer import KIND_SUFFIX, read_kinds
from pcc_ros.errors import ConfigError, DataError
from pcc_ros.geometry.boxes import iou_bev
from pcc_ros.types import Boxes

SEED = 7
LOW = Sensor.low_res()


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("synth")
    generate(root, sequences=2, frames=3, seed=SEED, sensor=LOW, progress=False)
    return root


def _world_points(root: Path, seq: str, frame: int) -> tuple[np.ndarray, np.ndarray]:
    """Written scan of a frame moved into the world frame with the written pose."""
    pts = np.fromfile(root / "training" / "velodyne" / seq / f"{frame:06d}.bin", np.float32).reshape(-1, 4)
    pose = np.loadtxt(root / "training" / "poses" / f"{seq}.txt", ndmin=2)[frame].reshape(3, 4)
    return pts[:, :3].astype(np.float64) @ pose[:, :3].T + pose[:, 3], pose[:, 3]


@pytest.mark.parametrize("family", FAMILIES)
def test_vehicle_meshes_are_closed_shaped_and_canonical(family):
    rng = np.random.default_rng(0)
    model = build_vehicle(family, rng)
    for c in range(model.mesh.n_components):  # body, four wheels (and pickup bed parts)
        assert is_closed_oriented(*model.mesh.component_mesh(c))
    assert model.mesh.n_components >= 5
    # Mesh is centred on its tight box.
    lo, hi = model.mesh.vertices.min(0), model.mesh.vertices.max(0)
    np.testing.assert_allclose(lo, -hi, atol=1e-9)
    np.testing.assert_allclose(hi - lo, model.size, atol=1e-9)
    # Shaped, not a box: the body's volume fills clearly less than the box.
    v = model.mesh.vertices[model.mesh.triangles]
    volume = np.einsum("ij,ij->i", v[:, 0], np.cross(v[:, 1], v[:, 2])).sum() / 6.0
    assert volume < 0.85 * np.prod(model.size)
    shape = canonical_shape(model, 16384, rng)
    assert shape.shape == (16384, 3) and shape.dtype == np.float32
    assert shape[:, 0].min() == pytest.approx(-0.5, abs=0.01) and shape[:, 0].max() == pytest.approx(0.5, abs=0.01)
    assert np.abs(shape[:, 0]).max() <= 0.5 + 1e-6


def test_vehicle_sizes_follow_kitti():
    rng = np.random.default_rng(1)
    from pcc_ros.data.synthetic.vehicles import random_vehicle

    models = [random_vehicle(rng) for _ in range(300)]
    cars = np.array([m.size for m in models if m.label == "Car"])
    vans = np.array([m.size for m in models if m.label == "Van"])
    assert np.abs(cars.mean(0) - [3.9, 1.6, 1.5]) .max() < 0.15, cars.mean(0)
    assert len(vans) > 5 and (vans.mean(0) > cars.mean(0)).all()
    assert cars[:, 0].std() > 0.2  # random proportions


def test_points_lie_on_surfaces_and_no_ray_passes_a_nearer_surface(dataset):
    street = build_sequence(SEED, 0, 3, "train")
    for frame in (0, 2):
        world, _ = street.world_at(frame)
        pts, origin = _world_points(dataset, "0000", frame)
        assert len(pts) > 3000
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor(world.vertices.astype(np.float32)),
                            o3d.core.Tensor(world.triangles.astype(np.uint32)))
        dist = scene.compute_distance(o3d.core.Tensor(pts.astype(np.float32))).numpy()
        sigma = LOW.range_noise
        assert np.quantile(dist, 0.999) < 5 * sigma and np.median(dist) < 2 * sigma
        # Re-cast from the sensor toward each return: nothing is hit clearly before it.
        d = pts - origin
        rng_ = np.linalg.norm(d, axis=1)
        rays = np.c_[np.broadcast_to(origin, d.shape), d / rng_[:, None]].astype(np.float32)
        first = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
        assert np.all(first >= rng_ - 6 * sigma)


def test_noise_free_returns_are_exact_first_hits():
    sensor = Sensor.low_res(range_noise=0.0, dropout=0.0)
    street = build_sequence(3, 0, 1, "train")
    origin, yaw = sensor_pose(street, 0, sensor)
    world, owner = street.world_at(0)
    scan = cast(sensor, world, owner, origin, yaw, np.random.default_rng(0))
    c, s = np.cos(yaw), np.sin(yaw)
    p = scan.points[:, :3].astype(np.float64)
    pw = np.c_[c * p[:, 0] - s * p[:, 1], s * p[:, 0] + c * p[:, 1], p[:, 2]] + origin
    scene = build_scene(world)
    dist = scene.compute_distance(o3d.core.Tensor(pw.astype(np.float32))).numpy()
    assert dist.max() < 3e-3
    np.testing.assert_allclose(np.linalg.norm(p, axis=1), scan.true_range, atol=2e-4 * scan.true_range.max())
    # Intensity in [0, 1); glass and dark tyres drop / dim, so not all returns are equal.
    assert 0 <= scan.points[:, 3].min() and scan.points[:, 3].max() < 1 and scan.points[:, 3].std() > 0.02


def _car_points_vs_distance(points: np.ndarray, boxes: Boxes) -> tuple[np.ndarray, np.ndarray]:
    """Points inside each box (rotated into the box frame, ground excluded) and box distance."""
    d = points[None, :, :3] - boxes.center[:, None, :]
    c, s = np.cos(boxes.yaw)[:, None], np.sin(boxes.yaw)[:, None]
    x, y = c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]
    half = boxes.size[:, None, :] / 2
    inside = (np.abs(x) <= half[..., 0]) & (np.abs(y) <= half[..., 1])
    inside &= (d[..., 2] <= half[..., 2]) & (d[..., 2] >= -half[..., 2] + 0.2)
    return inside.sum(1), np.linalg.norm(boxes.center[:, :2], axis=1)


def _loglog_fit(counts, dist):
    ok = (counts > 0) & (dist > 5) & (dist < 60)
    slope, intercept = np.polyfit(np.log(dist[ok]), np.log(counts[ok]), 1)
    return slope, np.exp(intercept + slope * np.log(20.0))


@pytest.mark.slow
def test_point_counts_fall_with_distance_like_kitti(shared_data):
    root = shared_data / "kitti_tracking" / "training"
    calib = Calibration.read(root / "calib" / "0000.txt")
    rows = parse_label_lines((root / "label_02" / "0000.txt").read_text().splitlines(), tracking=True)
    keep = np.isin(rows.type, ["Car", "Van"])
    rows = rows[keep]
    real_n, real_d = [], []
    for f in np.unique(rows.frame):
        pts = np.fromfile(root / "velodyne" / "0000" / f"{f:06d}.bin", np.float32).reshape(-1, 4)
        n, d = _car_points_vs_distance(pts, camera_to_lidar_boxes(rows[rows.frame == f], calib))
        real_n.append(n)
        real_d.append(d)
    obj = shared_data / "kitti_object" / "training"
    for i in range(6):
        cal = Calibration.read(obj / "calib" / f"{i:06d}.txt")
        r = parse_label_lines((obj / "label_2" / f"{i:06d}.txt").read_text().splitlines(), tracking=False)
        r = r[np.isin(r.type, ["Car", "Van"])]
        pts = np.fromfile(obj / "velodyne" / f"{i:06d}.bin", np.float32).reshape(-1, 4)
        n, d = _car_points_vs_distance(pts, camera_to_lidar_boxes(r, cal))
        real_n.append(n)
        real_d.append(d)
    real_slope, real_at20 = _loglog_fit(np.concatenate(real_n), np.concatenate(real_d))

    sensor = Sensor()  # the full 64-beam sensor, as in the real frames
    syn_n, syn_d = [], []
    for street_seed in (11, 12):
        res = simulate_frame(build_sequence(street_seed, 0, 1, "train"), 0, sensor, np.random.default_rng(0))
        # KITTI labels cover objects an annotator saw in the camera; compare with the not-heavily-occluded ones.
        cars = np.isin(res.gt.label, ["Car", "Van"]) & (res.occluded <= 1)
        n, d = _car_points_vs_distance(res.scan.points, res.gt[cars])
        syn_n.append(n)
        syn_d.append(d)
    syn_slope, syn_at20 = _loglog_fit(np.concatenate(syn_n), np.concatenate(syn_d))
    # Both fall roughly like 1 / d^2 (KITTI sample: about -2.3) and agree in level within a factor of 3.
    assert syn_slope < -1.5 and real_slope < -1.5
    assert abs(syn_slope - real_slope) < 0.7, (syn_slope, real_slope)
    assert 1 / 3 < syn_at20 / real_at20 < 3, (syn_at20, real_at20)


def test_layout_labels_round_trip_and_reader(dataset):
    meta = json.loads((dataset / "meta.json").read_text())
    assert meta["complete"] and meta["splits"] == {"train": ["0000"], "test": ["0001"]}
    for seq, split in (("0000", "train"), ("0001", "test")):
        for sub in ("training/label_02", "training/calib", "training/oxts", "training/poses"):
            assert (dataset / sub / f"{seq}.txt").is_file()
        assert len(list((dataset / "training" / "velodyne" / seq).glob("*.bin"))) == 3
        assert len(list((dataset / "detections" / "synthetic" / seq).glob("*.txt"))) == 3
        street = build_sequence(SEED, int(seq), 3, split)
        frames = list(KittiTracking(dataset).frames(seq, detections_dir=dataset / "detections" / "synthetic"))
        assert len(frames) == 3
        for f, frame in enumerate(frames):
            res = simulate_frame(street, f, LOW, seeded_rng(SEED, SPLIT_CODES[split], int(seq), 2, f))
            assert frame.ground_truth.equals(res.gt, atol=2e-6)
            assert frame.detections.equals(res.detections, atol=2e-6)
            kind_file = dataset / "detections" / "synthetic" / seq / f"{f:06d}{KIND_SUFFIX}"
            kinds = read_kinds(kind_file, len(res.detections))
            np.testing.assert_array_equal(kinds[0], res.detection_kind)
            np.testing.assert_array_equal(kinds[1], res.detection_source)
            np.testing.assert_array_equal(frame.points, res.scan.points)
            # Pose from oxts (devkit convention) = ego motion since the first frame.
            origin0, yaw0 = sensor_pose(street, 0, LOW)
            origin, _ = sensor_pose(street, f, LOW)
            c, s = np.cos(yaw0), np.sin(yaw0)
            dxy = origin[:2] - origin0[:2]
            np.testing.assert_allclose(frame.pose[:2, 3], [c * dxy[0] + s * dxy[1], -s * dxy[0] + c * dxy[1]],
                                       atol=2e-3)
        tracks = {int(t) for fr in frames for t, lab in zip(fr.ground_truth.track_id, fr.ground_truth.label)
                  if lab in ("Car", "Van")}
        for t in tracks:
            shape = load_shape(dataset, seq, t)
            assert shape is not None and shape.shape == (16384, 3)
            assert -0.51 < shape[:, 0].min() < -0.48 and 0.48 < shape[:, 0].max() < 0.51
        lines = (dataset / "training" / "oxts" / f"{seq}.txt").read_text().splitlines()
        assert all(len(line.split()) == 30 for line in lines)
    labels = {lab for seq in ("0000", "0001") for lab in parse_label_lines(
        (dataset / "training" / "label_02" / f"{seq}.txt").read_text().splitlines(), tracking=True).type}
    assert labels <= {"Car", "Van", "Pedestrian"} and {"Car", "Pedestrian"} <= labels


def test_train_and_test_shapes_are_disjoint(dataset):
    def shapes(seq):
        return {p.name: np.load(p) for p in (dataset / "shapes" / seq).glob("*.npy")}

    train, test = shapes("0000"), shapes("0001")
    assert train and test
    # Summaries of every shape: no test car repeats a training car.
    sig = lambda s: np.r_[s.min(0), s.max(0), s.std(0)]  # noqa: E731
    a = np.array([sig(s) for s in train.values()])
    b = np.array([sig(s) for s in test.values()])
    assert np.abs(a[:, None] - b[None]).max(-1).min() > 1e-3


@pytest.mark.slow  # generates the dataset twice more: 10 s of test-fast (load 13 on 2 cores)
def test_same_seed_same_bytes_and_resume(tmp_path, dataset):
    root = tmp_path / "again"
    generate(root, sequences=2, frames=3, seed=SEED, sensor=LOW, progress=False)
    files = sorted(p.relative_to(dataset) for p in dataset.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(root) for p in root.rglob("*") if p.is_file())
    for rel in files:
        assert (dataset / rel).read_bytes() == (root / rel).read_bytes(), rel
    # Resume: a deleted sequence is regenerated identically; finished ones are kept.
    (root / "training" / "label_02" / "0001.txt").unlink()
    (root / "training" / "velodyne" / "0001" / "000002.bin").unlink()
    generate(root, sequences=2, frames=3, seed=SEED, sensor=LOW, progress=False)
    for rel in files:
        assert (dataset / rel).read_bytes() == (root / rel).read_bytes(), rel
    # A finished dataset re-run as it was made writes nothing: every file keeps its time, so a
    # cache extracted from it (its fingerprint reads the times) stays valid.
    times = {rel: (root / rel).stat().st_mtime_ns for rel in files}
    generate(root, sequences=2, frames=3, seed=SEED, sensor=LOW, progress=False)
    assert {rel: (root / rel).stat().st_mtime_ns for rel in files} == times
    with pytest.raises(ConfigError):
        generate(root, sequences=2, frames=3, seed=SEED + 1, sensor=LOW, progress=False)
    other = tmp_path / "other"
    generate(other, sequences=1, frames=1, seed=SEED + 1, sensor=LOW, progress=False)
    assert (other / "training/velodyne/0000/000000.bin").read_bytes() != (
        root / "training/velodyne/0000/000000.bin").read_bytes()


def test_load_shape_errors(tmp_path):
    assert load_shape(tmp_path, "0000", 3) is None
    bad = tmp_path / "shapes" / "0000"
    bad.mkdir(parents=True)
    (bad / "3.npy").write_bytes(b"not numpy")
    with pytest.raises(DataError, match=r"3\.npy"):
        load_shape(tmp_path, "0000", 3)
    np.save(bad / "4.npy", np.zeros((10, 2), np.float32))
    with pytest.raises(DataError, match="expected"):
        load_shape(tmp_path, 0, 4)


def test_detector_misses_sparse_cars_and_scores_false_ones_lower():
    rng = np.random.default_rng(0)
    levels = np.array([0, 3, 30, 300])
    centre = np.array([[10.0, -8, -0.9], [20, 0, -0.9], [30, 8, -0.9], [15, 16, -0.9]])  # far apart
    gt = Boxes(centre, np.tile([4.0, 1.7, 1.5], (4, 1)), [0.3, -1.0, 2.0, 0.0])
    clutter = Boxes([[12.0, -20, -1.2], [25, 20, -1.2]], np.tile([2.0, 1.0, 1.0], (2, 1)), np.zeros(2))
    ground = np.c_[rng.uniform(5, 40, 200), rng.uniform(-30, 30, 200), np.full(200, -1.73)]
    found, true_scores, false_scores, errors = np.zeros(4), [], [], []
    runs = 400
    for _ in range(runs):  # one simulated frame per run
        dets, kind, _ = detect(gt, levels, clutter, np.array([100, 100]), np.array([0.3, 0.3]), ground, -1.73, rng,
                               DetectorParams(misplaced_probability=0.0, duplicate_probability=0.0, far_rate=0.0))
        true = kind == "true"
        td = dets[true]
        nearest = np.argmin(np.linalg.norm(td.center[:, None, :2] - centre[None, :, :2], axis=2), axis=1)
        found[nearest] += 1
        errors.extend(np.linalg.norm(td.center - centre[nearest], axis=1))
        true_scores.extend(td.score)
        false_scores.extend(dets.score[~true])
    rate = found / runs
    assert rate[0] == 0 and rate[1] < 0.4 and rate[2] > 0.8 and rate[3] > 0.97, rate
    assert 0.3 * 2 * runs < len(false_scores) < 2.5 * runs  # clutter (0.3 each) + ghosts (~0.6)
    true_scores, false_scores = np.array(true_scores), np.array(false_scores)
    assert np.median(true_scores) > np.median(false_scores) + 0.2
    assert false_scores.max() > np.quantile(true_scores, 0.2)  # overlapping, not separable by a threshold
    assert 0.01 < np.median(errors) < 0.5


def test_scene_has_traffic_clutter_and_moving_tracks():
    street = build_sequence(5, 0, 20, "train")
    kinds = [o.name for o in street.objects]
    for name in ("pole", "pedestrian", "building", "sidewalk"):
        assert name in kinds
    assert {"bush", "blob", "low_wall"} & set(kinds)
    assert {"bollard", "sign", "bicycle", "fence"} & set(kinds)
    vehicles = [o for o in street.objects if o.kind == KIND_VEHICLE]
    assert any(o.moving for o in vehicles) and any(not o.moving for o in vehicles)
    assert len({o.track_id for o in vehicles}) == len(vehicles)


@pytest.mark.parametrize("name", sorted(BUILDERS))
def test_furniture_meshes_are_closed_with_real_proportions(name):
    extents = {"bollard": ((0.15, 0.25), (0.8, 1.2)), "sign": ((0.6, 0.95), (2.0, 2.7)),
               "bicycle": ((1.6, 1.9), (0.95, 1.15)), "fence": ((4.0, 12.1), (1.0, 1.85))}
    mesh = BUILDERS[name](np.random.default_rng(3))
    for c in range(mesh.n_components):
        assert is_closed_oriented(*mesh.component_mesh(c)), (name, c)
    size = mesh.vertices.max(0) - mesh.vertices.min(0)
    (lo, hi), (zlo, zhi) = extents[name]
    assert lo <= size[:2].max() <= hi and zlo <= size[2] <= zhi, size
    assert mesh.vertices[:, 2].min() > -1e-9  # stands on z = 0


def test_detector_produces_and_labels_every_false_positive_kind():
    """Each of the four kinds appears, is labelled, and sits where its definition says."""
    rng = np.random.default_rng(1)
    centre = np.array([[10.0, -8, -0.9], [20, 0, -0.9], [30, 8, -0.9]])
    gt = Boxes(centre, np.tile([4.0, 1.7, 1.5], (3, 1)), [0.3, -1.0, 2.0])
    clutter = Boxes([[12.0, -20, -1.2], [25, 20, -1.2]], np.tile([0.2, 0.2, 1.0], (2, 1)), np.zeros(2))
    r, a = rng.uniform(5, 75, 4000), rng.uniform(-np.pi, np.pi, 4000)
    ground = np.c_[r * np.cos(a), r * np.sin(a), np.full(4000, -1.73)]
    params = DetectorParams(misplaced_probability=0.2, duplicate_probability=0.2, far_rate=1.0, empty_space_rate=1.0)
    seen: dict[str, list] = {k: [] for k in KINDS}
    for _ in range(60):
        dets, kind, source = detect(gt, np.array([300, 300, 300]), clutter, np.array([50, 50]), np.array([0.5, 0.5]),
                                    ground, -1.73, rng, params, np.array(["bollard", "bicycle"], dtype=object))
        assert len(kind) == len(source) == len(dets) and set(kind) <= set(KINDS)
        assert np.all(dets.score[:-1] >= dets.score[1:])  # sorted by score, kinds kept aligned
        for k in KINDS:
            seen[k].append((dets[kind == k], source[kind == k]))
    for k in KINDS:
        assert sum(len(b) for b, _ in seen[k]) > 5, k
    gt_iou = lambda b: iou_bev(b, gt).max(axis=1)  # noqa: E731
    true = Boxes.concatenate([b for b, _ in seen["true"]])
    assert np.median(gt_iou(true)) > 0.6
    moved = Boxes.concatenate([b for b, _ in seen["misplaced"]])
    assert (gt_iou(moved) < 0.3).all() and (gt_iou(moved) > 0.0).mean() > 0.5  # beside a real car
    conf = Boxes.concatenate([b for b, _ in seen["confusion"]])
    assert (np.linalg.norm(conf.center[:, None, :2] - clutter.center[None, :, :2], axis=2).min(1) < 1.5).all()
    assert set(np.concatenate([s for _, s in seen["confusion"]])) <= {"bollard", "bicycle"}
    ghost = Boxes.concatenate([b for b, _ in seen["ghost"]])
    far = Boxes.concatenate([b for b, _ in seen["far"]])
    g_range, f_range = np.linalg.norm(ghost.center[:, :2], axis=1), np.linalg.norm(far.center[:, :2], axis=1)
    assert g_range.max() < 46 and f_range.min() > 44 and f_range.max() < 76
    assert (ghost.center[:, 2] - ghost.size[:, 2] / 2 > -1.73 + 0.3).any()  # some float in empty space
    for k in FALSE_KINDS:
        assert all((s == "-").all() for _, s in seen[k]) or k == "confusion"
