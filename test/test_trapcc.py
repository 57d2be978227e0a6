"""TraPCC: the network, the scene graph, training steps and checkpoints, on synthetic tracks
with known answers (the ground-truth pools' tests are in test_trapcc_pools)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from conftest import assert_named_failure, run_cli

from pcc_ros.data.instances import ExtractConfig, extract_instances
from pcc_ros.errors import ConfigError
from pcc_ros.geometry.canonical import from_canonical, to_canonical
from pcc_ros.models import SceneContext, create, load_completer
from pcc_ros.models.base import aspect_scales, median_box_aspect
from pcc_ros.models.recipe import BOX_REFLECTION, IDENTITY, plane_placement, plane_reflection
from pcc_ros.models.trapcc import nearest_neighbours, neighbour_geometry
from pcc_ros.models.trapcc_recipe import TrainOptions, TraPCCRecipe, training_recipe
from pcc_ros.types import Boxes, Sample
from pcc_ros.workflows.train import load_recipe, training_kit

ELLIPSOID = np.array([4.0, 1.8, 1.5])
BOXY = np.array([4.1, 1.8, 1.5])
VAN = np.array([5.2, 2.1, 2.2])

#: A tiny network so the tests run in seconds on a shared CPU.
TINY = {
    "half_encoder_widths1": [16], "half_encoder_widths2": [32], "half_decoder_widths": [32], "half_points": 32,
    "encoder_widths1": [16], "encoder_widths2": [32], "decoder_fc_widths": [64], "coarse_points": 64,
    "fold_widths": [16], "neighbour_encoder_widths1": [8], "neighbour_encoder_widths2": [16], "attention_dim": 16,
    "neighbour_points": 64, "max_input_points": 256,
}


def ellipsoid_surface(n: int, size: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Canonical points and outward normals of an ellipsoidal car of ``size``."""
    half = size / size[0] / 2.0 * 0.95
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d * half, d / half


def box_surface(n: int, size: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Canonical points and outward normals on the faces of a box-shaped car."""
    half = size / size[0] / 2.0 * 0.95
    axis = rng.integers(0, 3, n)
    sign = rng.choice([-1.0, 1.0], n)
    pts = rng.uniform(-1, 1, (n, 3))
    pts[np.arange(n), axis] = sign
    normals = np.zeros((n, 3))
    normals[np.arange(n), axis] = sign
    return pts * half, normals


def track_frames(surface, size, sequence, track, n_frames, drive_by=True, seed=0, density=0.15):
    """Frames of one car: turning on the spot in front of the sensor (seen all round over the
    track) or parked (one side only)."""
    rng = np.random.default_rng(seed)
    pts_c, normals = surface
    frames = []
    for f in range(n_frames):
        center = np.array([8.0, 3.0, -0.9]) if drive_by else np.array([0.5, 8.0, -0.9])
        yaw = 2 * np.pi * f / n_frames if drive_by else 0.0  # parked: only its right side is ever seen
        origin = to_canonical(np.zeros((1, 3)), center, yaw, size[0])[0]
        seen = np.einsum("ij,ij->i", normals, origin - pts_c) > 0
        seen &= rng.random(len(pts_c)) < density
        car = from_canonical(pts_c[seen] + rng.normal(0, 0.002, (seen.sum(), 3)), center, yaw, size[0])
        boxes = Boxes([center], [size], [yaw], label=["Car"], track_id=[track])
        points = np.c_[car, np.zeros(len(car))].astype(np.float32)
        frames.append(Sample(stamp_ns=f * 100_000_000, frame_id="velodyne", points=points, ground_truth=boxes,
                            sequence=sequence, index=f))
    return frames



# --------------------------------------------------------------------------- scene graph


def test_scene_graph_neighbours_are_the_k_nearest_within_radius():
    centers = np.array([[0.0, 0, 0], [5, 0, 0], [0, 3, 0], [30, 0, 0], [-4, 0, 0], [0, -6, 0]])
    near = nearest_neighbours(centers, k=3, radius=10.0)
    assert near[0].tolist() == [2, 4, 1]  # 3 m, 4 m, 5 m; the 6 m one is the fourth
    assert near[3].tolist() == [-1, -1, -1]  # 25 m from everything: isolated
    assert near[1].tolist() == [0, 2, 5]  # 5, sqrt(34), sqrt(61)
    boxes = Boxes(centers, np.tile(ELLIPSOID, (6, 1)), np.zeros(6), label=["Car"] * 6)
    clouds = [np.random.default_rng(i).normal(0, 0.1, (20, 3)).astype(np.float32) for i in range(6)]
    ctx = SceneContext.from_frame(boxes, clouds)[0].nearest(3, 10.0)
    assert np.allclose(ctx.neighbour_boxes.center, centers[[2, 4, 1]])  # the same rule online


def test_neighbour_geometry_marks_occluders_between_target_and_sensor():
    center = np.array([20.0, 0.0, 0.0])
    nbs = np.array([[12.0, 0.0, 0.0], [28.0, 0.0, 0.0], [20.0, 6.0, 0.0]])
    g = neighbour_geometry(center, 0.0, 4.0, nbs, np.array([0.0, np.pi / 2, 0.0]), radius=20.0)
    assert g.shape == (3, 7)
    assert g[0, 6] == pytest.approx(1.0) and g[1, 6] == pytest.approx(-1.0) and abs(g[2, 6]) < 1e-9
    assert g[0, 5] == pytest.approx(8.0 / 20.0)  # distance / radius
    assert g[1, 3] == pytest.approx(1.0) and g[1, 4] == pytest.approx(0.0, abs=1e-9)  # sin, cos of the yaw


def _frame_contexts(n=4, isolated=True):
    centers = np.array([[10.0, 0, 0], [14.0, 3, 0], [9.0, -4, 0], [60.0, 0, 0]])[:n]
    boxes = Boxes(centers, np.tile(ELLIPSOID, (n, 1)), np.zeros(n), label=["Car"] * n)
    rng = np.random.default_rng(3)
    clouds = [ellipsoid_surface(200, ELLIPSOID, rng)[0].astype(np.float32) for _ in range(n)]
    return clouds, SceneContext.from_frame(boxes, clouds)


def test_scene_graph_changes_only_cars_with_neighbours():
    torch.manual_seed(0)
    net = create("trapcc", device="cpu", **TINY)
    clouds, contexts = _frame_contexts()
    without = net.complete(clouds)
    with_ctx = net.complete(clouds, contexts)
    # zero-initialised scene projection: an untrained scene graph changes nothing (CP-Net)
    assert all(np.allclose(a, b, atol=1e-6) for a, b in zip(without, with_ctx))
    with torch.no_grad():
        net.model.scene_out.weight.normal_(0, 0.5)
    with_ctx = net.complete(clouds, contexts)
    without = net.complete(clouds)
    changed = [not np.allclose(a, b, atol=1e-6) for a, b in zip(without, with_ctx)]
    assert changed == [True, True, True, False]  # the car 50 m away has no neighbour within 20 m
    cpnet = create("trapcc", device="cpu", scene_graph="none", **TINY)
    assert not hasattr(cpnet.model, "nb_encoder")


def test_completion_contract_and_batch_independence():
    torch.manual_seed(0)
    net = create("trapcc", device="cpu", batch_size=2, **TINY)
    rng = np.random.default_rng(0)
    front_only = ellipsoid_surface(300, ELLIPSOID, rng)[0]
    front_only = front_only[front_only[:, 0] > 0.05]
    clouds = [ellipsoid_surface(900, ELLIPSOID, rng)[0], front_only, np.array([[0.1, 0.2, 0.0]])]
    out = net.complete(clouds)
    assert [o.shape for o in out] == [(net.num_output_points, 3)] * 3
    alone = net.complete([clouds[1]])[0]
    assert np.allclose(alone, out[1], atol=1e-5)  # a cloud's completion does not depend on the batch
    with pytest.raises(ConfigError):
        create("trapcc", device="cpu", scene_graph="transformer")


# --------------------------------------------------------------------------- training


@pytest.fixture(scope="module")
def train_cache(tmp_path_factory):
    rng = np.random.default_rng(1)
    frames = []
    for t in range(3):  # three drive-by tracks, two cars per frame so the scene graph has neighbours
        a = track_frames(ellipsoid_surface(5000, ELLIPSOID, rng), ELLIPSOID, f"000{t}", "1", 12, seed=t)
        b = track_frames(box_surface(5000, BOXY, rng), BOXY, f"000{t}", "2", 12, seed=10 + t)
        for fa, fb in zip(a, b):
            fb_points = fb.points.copy()
            fb_points[:, 1] += 6.0  # the second car in the next lane
            boxes = Boxes(np.r_[fa.ground_truth.center, fb.ground_truth.center + np.array([0, 6.0, 0])],
                          np.r_[fa.ground_truth.size, fb.ground_truth.size], np.zeros(2), label=["Car", "Car"],
                          track_id=["1", "2"])
            frames.append(Sample(fa.stamp_ns, "velodyne", np.r_[fa.points, fb_points], ground_truth=boxes,
                                sequence=fa.sequence, index=fa.index))
    cfg = ExtractConfig(val_fraction=0.0, test_fraction=0.0, ground_margin=0.0)
    return extract_instances(frames, tmp_path_factory.mktemp("train") / "cache", cfg, progress=False)


def _recipe(tmp_path, **model):
    recipe = training_recipe(gt_dir=str(tmp_path / "gt"), min_points_pool=512, **{**TINY, **model})
    recipe.kit = training_kit()  # what pcc train hands it: caches and ground-truth pools
    return recipe


def test_training_data_never_touches_complete_shapes_and_has_neighbours(train_cache, tmp_path):
    recipe = _recipe(tmp_path)
    data = recipe.training_data(train_cache, "train", min_points=10)
    assert len(data) == len(train_cache.indices("train", min_points=10))
    assert (data.whole >= 0).all()
    assert (data.neighbours[:, 0] >= 0).all() and (data.neighbours[:, 1:] == -1).all()  # one other car per frame
    summary = recipe.data_summary()
    assert summary["complete_shapes_used"] is False and summary["real_instances"] == 0


def test_recipe_without_the_training_kit_names_itself(train_cache, tmp_path):
    """models/ never imports data/: caches and pools come from pcc_ros.workflows.train (load_recipe sets the kit)."""
    recipe = training_recipe(gt_dir=str(tmp_path / "gt"), **TINY)
    with pytest.raises(ConfigError, match=r"trapcc: .*training_kit"):
        recipe.training_data(train_cache, "train")
    assert load_recipe("trapcc", "default", {"gt_dir": str(tmp_path / "gt")}).kit == training_kit()


def test_box_aspect_training_scales_inputs_and_targets_by_their_own_boxes(train_cache, tmp_path):
    """The node completes in the box-aspect frame: training inputs get their box's factors, every
    pseudo-GT entry its own track's, neighbours stay in their own canonical frame (as the
    pipeline's SceneContext gives them), and the completer validates and is saved in that frame."""
    plain = _recipe(tmp_path).training_data(train_cache, "train", min_points=10)
    recipe = _recipe(tmp_path, box_aspect=True)
    data = recipe.training_data(train_cache, "train", min_points=10)
    sel = train_cache.indices("train", min_points=10)
    sizes = train_cache.meta["box_size"][sel]
    aspect = median_box_aspect(sizes)
    assert recipe.aspect == pytest.approx(aspect) and recipe.data_summary()["box_aspect"] == pytest.approx(aspect)
    scales = aspect_scales(sizes, aspect, len(sel))
    assert not np.allclose(scales, 1.0)  # two box shapes: each is moved onto the median
    for i in (0, len(sel) // 2, len(sel) - 1):
        np.testing.assert_allclose(data.clouds[i], plain.clouds[i] * scales[i], rtol=1e-6)
    for part in ("whole", "front", "back"):
        before, after = plain.pools.part(part), data.pools.part(part)
        if len(before):
            own = aspect_scales(before.size, aspect, len(before))
            np.testing.assert_allclose(after.points, before.points * own[:, None, :], rtol=1e-6)
    assert all(np.array_equal(a, b) for a, b in zip(data.nb_clouds, plain.nb_clouds))
    np.testing.assert_array_equal(data.whole, plain.whole)  # retrieval itself is frame-independent
    completer = recipe.build_completer("cpu")
    recipe.prepare(completer, data, [], 0)
    assert completer.box_aspect == pytest.approx(aspect)
    assert recipe.describe()["reference_aspect"] == pytest.approx(list(aspect))


def test_held_out_sources_are_refused_and_recorded(train_cache, tmp_path):
    """A cache extracted from a held-out dataset (what pcc eval --real scores) cannot reach training."""
    source = tmp_path / "real" / "kitti_tracking"
    source.mkdir(parents=True)
    frames = [f for f in track_frames(ellipsoid_surface(3000, VAN, np.random.default_rng(4)), VAN, "0000", "7", 4,
                                      seed=4)]
    held = extract_instances(frames, tmp_path / "held_cache", ExtractConfig(val_fraction=0.0, test_fraction=0.0),
                             source=source, progress=False)
    recipe = _recipe(tmp_path, real_data=[str(held.root)], held_out=[str(source.parent)])
    with pytest.raises(ConfigError, match=r"^trapcc: cache .*held out"):
        recipe.training_data(train_cache, "train")
    recipe = _recipe(tmp_path, pool_data=[str(held.root)], held_out=[str(source)])
    with pytest.raises(ConfigError, match="held out"):  # pools are training data too
        recipe.training_data(train_cache, "train")
    recipe = _recipe(tmp_path, held_out=[str(source)])
    recipe.training_data(train_cache, "train")
    summary = recipe.data_summary()
    assert summary["held_out"]["sources"] == [str(source.resolve())]
    assert summary["sources"][0]["crop"]["ground_margin"] == 0.0


@pytest.mark.slow
@pytest.mark.parametrize("model", [{}, {"pnet": False, "scene_graph": "none"}, {"scene_graph": "mean"}])
def test_a_few_training_steps_lower_the_loss(train_cache, tmp_path, model):
    torch.manual_seed(0)
    recipe = _recipe(tmp_path, **model)
    data = recipe.training_data(train_cache, "train")
    completer = recipe.build_completer("cpu")
    net = completer.model
    net.train()
    batch = next(recipe.batches(data, 8, completer.config, np.random.default_rng(0)))
    optimizer = torch.optim.Adam(net.parameters(), lr=2e-3)
    first, stats = recipe.loss(net, batch)
    assert ("partial" in stats) == (model.get("pnet", True))
    for _ in range(40):
        loss, _ = recipe.loss(net, batch)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    last, _ = recipe.loss(net, batch)
    assert float(last.detach()) < 0.7 * float(first.detach())


def test_symmetric_options_mirror_the_targets_and_penalise_a_lopsided_output(train_cache, tmp_path):
    """``mirror_targets`` / ``symmetry_weight``: the far flank is asked for (docs/pointpncnet.md, far side)."""
    torch.manual_seed(0)
    plain = _recipe(tmp_path)
    data = plain.training_data(train_cache, "train")
    completer = plain.build_completer("cpu")
    batch = next(plain.batches(data, 4, completer.config, np.random.default_rng(0)))
    sym = _recipe(tmp_path, mirror_targets=True, symmetry_weight=1.0)
    _, base = plain.loss(completer.model, batch)
    _, stats = sym.loss(completer.model, batch)
    assert "symmetry" not in base and stats["symmetry"] > 0  # an untrained network's output is not symmetric
    assert stats["whole"] != base["whole"]  # the Whole-GT term now also reaches for the reflected targets
    # the symmetry term is 0 for a symmetric cloud and grows with the lean
    from pcc_ros.models.losses import reflect_y, symmetry_chamfer

    cloud = torch.rand(1, 256, 3) - 0.5
    both = torch.cat([cloud, reflect_y(cloud)], 1)
    assert float(symmetry_chamfer(both)) < 1e-3 < float(symmetry_chamfer(cloud + torch.tensor([0.0, 0.3, 0.0])))


def test_balance_term_sees_where_the_points_are(train_cache, tmp_path):
    """Both flanks drawn, three quarters of the points on one: the Chamfer symmetry term is blind to it,
    the density term is not, and its gradient moves points towards the sparse flank."""
    from pcc_ros.models.losses import reflect_y, symmetry_chamfer, symmetry_density

    rng = np.random.default_rng(0)
    flank = np.column_stack([rng.uniform(-0.5, 0.5, 400), rng.uniform(0.15, 0.2, 400), rng.uniform(0, 0.3, 400)])
    both = torch.tensor(np.concatenate([flank, flank * [1, -1, 1]])[None], dtype=torch.float32)
    lean = torch.tensor(np.concatenate([flank, flank[:134] * [1, -1, 1]])[None], dtype=torch.float32,
                        requires_grad=True)
    shifted = both + torch.tensor([0.0, 0.05, 0.0])  # a 5 cm asymmetry of the shape itself, for scale
    assert float(symmetry_density(both)) < 1e-6 and float(symmetry_density(reflect_y(both))) < 1e-6
    # the Chamfer term reads the lean as a fifth of the 5 cm shift; the density term as more than it
    assert float(symmetry_chamfer(lean.detach())) < 0.2 * float(symmetry_chamfer(shifted))
    assert float(symmetry_density(lean.detach())) > float(symmetry_density(shifted))
    symmetry_density(lean).backward()
    assert float(lean.grad[0, :400, 1].sum()) > 0  # descent moves the dense flank's points towards -y
    # wired into the recipe as an option, reported in the loss statistics
    data_recipe = _recipe(tmp_path, mirror_targets=True, balance_weight=1.0)
    data = data_recipe.training_data(train_cache, "train")
    completer = data_recipe.build_completer("cpu")
    batch = next(data_recipe.batches(data, 4, completer.config, np.random.default_rng(0)))
    _, stats = data_recipe.loss(completer.model, batch)
    assert stats["balance"] > 0


def test_flipped_batches_are_the_mirror_world(train_cache, tmp_path):
    """flip_prob: a flipped batch is the same draw with every input, target and neighbour reflected
    across the box's x-z plane, the neighbours' geometry as neighbour_geometry gives it in the
    mirror world."""
    from pcc_ros.errors import ConfigError
    from pcc_ros.models.trapcc_recipe import GEOMETRY_MIRROR

    plain, flipped = _recipe(tmp_path), _recipe(tmp_path, flip_prob=1.0)
    data = plain.training_data(train_cache, "train")
    cfg = plain.build_completer("cpu").config
    chosen = np.arange(min(6, len(data)))
    skip = np.random.default_rng(3)
    skip.random()  # the flipped batch draws its coin first; the plain one starts after it
    a, b = plain.make_batch(data, chosen, cfg, skip), flipped.make_batch(data, chosen, cfg, np.random.default_rng(3))
    mirror = torch.tensor([1.0, -1.0, 1.0])
    for name in ("points", "inputs", "whole", "half"):
        torch.testing.assert_close(getattr(b, name), getattr(a, name) * mirror)
    torch.testing.assert_close(b.neighbours.points, a.neighbours.points * mirror)
    assert b.neighbours.mask.any()
    torch.testing.assert_close(b.neighbours.geometry, a.neighbours.geometry * torch.from_numpy(GEOMETRY_MIRROR))
    # the constant is the mirror world's geometry
    rng = np.random.default_rng(0)
    center, nb, nb_yaw, origin = rng.normal(size=3), rng.normal(size=(3, 3)) * 5, rng.normal(size=3), rng.normal(size=3)
    yaw = 0.3
    m = np.array([1.0, -1.0, 1.0])
    np.testing.assert_allclose(neighbour_geometry(center * m, -yaw, 4.2, nb * m, -nb_yaw, 20.0, origin * m),
                               neighbour_geometry(center, yaw, 4.2, nb, nb_yaw, 20.0, origin) * GEOMETRY_MIRROR,
                               atol=1e-6)
    with pytest.raises(ConfigError, match="flip_prob"):
        _recipe(tmp_path, flip_prob=1.0, mirror_plane="label").make_batch(data, chosen, cfg, np.random.default_rng(0))


def test_real_share_oversamples_the_real_cache(train_cache, tmp_path):
    recipe = _recipe(tmp_path, real_data=[str(train_cache.root)], real_share=0.9)
    data = recipe.training_data(train_cache, "train")
    assert data.real.sum() == len(data) // 2  # the same cache twice: half of the instances are "real"
    drawn = np.random.default_rng(0).choice(len(data), 4000, p=recipe.sampling_weights(data))
    assert 0.87 < data.real[drawn].mean() < 0.93
    summary = recipe.data_summary()
    assert summary["real_share_of_samples"] == 0.9 and summary["real_fraction_of_instances"] == 0.5
    with pytest.raises(ConfigError):
        TraPCCRecipe(options=TrainOptions(real_share=1.5))


def test_checkpoint_round_trip(tmp_path):
    torch.manual_seed(0)
    net = create("trapcc", device="cpu", scene_graph="mean", **TINY)
    path = net.save(tmp_path / "t.safetensors", training={"steps": 3}, metrics={"val_cd_l1": 0.1})
    loaded = load_completer("trapcc", path, device="cpu")
    assert loaded.config == net.config and loaded.checkpoint_config["training"]["steps"] == 3
    clouds, contexts = _frame_contexts()
    with torch.no_grad():
        net.model.scene_out.weight.normal_(0, 0.5)
    path = net.save(tmp_path / "t.safetensors")
    loaded = load_completer("trapcc", path, device="cpu")
    for a, b in zip(net.complete(clouds, contexts), loaded.complete(clouds, contexts)):
        assert np.array_equal(a, b)


def test_gt_free_metrics_on_known_clouds():
    from pcc_ros.metrics.gtfree import gt_free_metrics

    whole = np.array([[0.2, 0.0, 0.0], [-0.2, 0.0, 0.0]])
    pred = np.array([[0.2, 0.0, 0.1], [-0.2, 0.0, 0.0]])
    partial = np.array([[-0.2, 0.1, 0.0]])
    m = gt_free_metrics(pred, partial, {"whole": whole, "front": np.array([[0.2, 0.0, 0.0]]), "back": None})
    # whole: (0.01 + 0) / 2 both ways = 0.01; front half [0.2, 0, 0.1] vs [0.2, 0, 0]: 0.01 + 0.01
    assert m["l_g"] == pytest.approx((0.01 + 0.02) / 2)
    assert m["l_i"] == pytest.approx(0.01)  # the input point is 0.1 from the prediction
    assert m["l_s"] == pytest.approx(0.01)  # side view (x-z): like the whole 3D Chamfer here
    assert m["mean_cd"] == pytest.approx((m["l_g"] + m["l_i"] + m["l_s"]) / 3)


@pytest.mark.slow
def test_pcc_train_trapcc_end_to_end_with_resume(train_cache, tmp_path, capsys, caplog):
    import json

    from pcc_ros.cli.main import main
    from pcc_ros.models.checkpoint import load_config

    out = tmp_path / "run"
    argv = ["train", "trapcc", "--data", str(train_cache.root), "--out", str(out), "--batch-size", "4",
            "--val-instances", "0", "--checkpoint-every", "2", "--no-progress", "--device", "cpu",
            "--option", f"gt_dir={tmp_path / 'gt'}", "--option", "min_points_pool=512",
            *(a for k, v in TINY.items() for a in ("--option", f"{k}={json.dumps(v)}"))]
    assert main([*argv, "--iterations", "3"]) == 0
    assert json.loads(capsys.readouterr().out)["step"] == 3
    config = load_config(out / "trapcc.json")
    summary = config["training"]["data_summary"]
    assert summary["complete_shapes_used"] is False and summary["instances"] > 0
    assert config["hyper_parameters"]["scene_graph"] == "attention"
    assert config["training"]["recipe"]["half_points"] == 32
    assert main([*argv, "--iterations", "5", "--resume"]) == 0
    assert json.loads(capsys.readouterr().out)["step"] == 5
    loaded = load_completer("trapcc", out / "trapcc.safetensors", device="cpu")
    assert loaded.complete([np.random.default_rng(0).normal(size=(40, 3)) * 0.2])[0].shape == (256, 3)
    assert_named_failure(*run_cli([*argv, "--iterations", "2", "--no-inpainting"], caplog),
                         "--no-inpainting is PointPnCNet's ablation", "--option scene_graph=none")
    # the generic --real-data / --real-share flags reach TraPCC's own mixing (and its pools)
    mixed = tmp_path / "mixed"
    argv_mixed = [a if a != str(out) else str(mixed) for a in argv]
    assert main([*argv_mixed, "--iterations", "1", "--real-data", str(train_cache.root), "--real-share", "0.3"]) == 0
    summary = load_config(mixed / "trapcc.json")["training"]["data_summary"]
    assert summary["real_instances"] > 0 and summary["real_share_of_samples"] == 0.3


def test_half_precision_with_neighbours():
    """half_precision on the CPU runs the network in bfloat16 (its weights are bfloat16) with the
    scene-graph neighbours: the same weights give float32 outputs that differ from the full
    precision run's by bfloat16 rounding only."""
    torch.manual_seed(0)
    net = create("trapcc", device="cpu", half_precision=True, **TINY)
    torch.manual_seed(0)
    full = create("trapcc", device="cpu", **TINY)
    assert {p.dtype for p in net.model.parameters()} == {torch.bfloat16}
    assert {p.dtype for p in full.model.parameters()} == {torch.float32}
    clouds, contexts = _frame_contexts()
    out, ref = net.complete(clouds, contexts), full.complete(clouds, contexts)
    assert all(o.dtype == np.float32 and np.isfinite(o).all() for o in out)
    diff = np.concatenate([np.abs(o - r).ravel() for o, r in zip(out, ref)])
    scale = np.concatenate([np.abs(r).ravel() for r in ref]).mean()
    assert diff.max() > 0 and np.median(diff) < 0.05 * scale, (np.median(diff), scale)  # rounded, not another net


def test_shipped_weights_record_their_training_data():
    from pcc_ros.models import default_checkpoint

    if default_checkpoint("trapcc") is None:
        pytest.skip("no shipped TraPCC weights")
    net = load_completer("trapcc", device="cpu")
    training = net.checkpoint_config["training"]
    assert training["data_summary"]["complete_shapes_used"] is False
    assert training["data_summary"]["real_instances"] > 0 and training["steps"] > 0
    # out of sample on what `pcc eval --real` scores (KITTI tracking), trained in the node's frame and crop
    summary = training["data_summary"]
    assert any(h.endswith("kitti_tracking") for h in summary["held_out"]["sources"])
    used = [s["source"] for s in summary["sources"] + summary["pool_sources"]]
    assert used and not any("kitti_tracking" in str(s) for s in used)
    assert summary["box_aspect"] == pytest.approx(list(net.box_aspect), abs=1e-5)
    assert all(s["crop"]["margin"] > 0 for s in summary["sources"])  # inputs cropped as the node crops
    clouds, contexts = _frame_contexts()
    out = net.complete(clouds, contexts)
    assert [o.shape for o in out] == [(2048, 3)] * len(clouds)


class _FixedOutput(torch.nn.Module):
    """A stand-in network with a given output, so a loss term can be read for a known prediction."""

    def __init__(self, detailed: torch.Tensor, coarse: torch.Tensor) -> None:
        super().__init__()
        self.detailed, self.coarse = detailed, coarse

    def forward(self, *args) -> dict[str, torch.Tensor]:
        present = torch.ones(self.coarse.shape[:2], dtype=torch.bool)
        return {"detailed": self.detailed, "coarse": self.coarse, "present": present}


def test_mirrored_halves_across_the_labelled_plane_ask_for_the_true_far_flank(train_cache, tmp_path):
    """``mirror_halves``: the Partial-GT halves (retrieved to fit the input, so leaning to its flank) are
    joined by their reflection; with ``mirror_plane="label"`` across the car's plane, not the box's, as
    PointPnCNet's targets (one copy: ``models.recipe.CarPlanes``). A coarse output on the whole true car
    then scores better than one on the seen flank only, and only the labelled plane makes it so."""
    recipe = _recipe(tmp_path, mirror_plane="label", mirror_targets=True, mirror_halves=True)
    data = recipe.training_data(train_cache, "train", min_points=10)
    # crops of labelled boxes: every observation reflects across its own box's plane, recorded as such
    assert data.reflection.shape == (len(data), 3, 4)
    np.testing.assert_array_equal(data.reflection, np.broadcast_to(BOX_REFLECTION, data.reflection.shape))
    assert recipe.data_summary()["sources"][0]["mirror_plane"] == {"label": 0, "unmatched": 0}
    np.testing.assert_array_equal(data.placement, np.broadcast_to(IDENTITY, data.placement.shape))
    assert _recipe(tmp_path).training_data(train_cache, "train", min_points=10).reflection is None
    config = recipe.build_completer("cpu").config
    # a detector box 0.1 to the car's right, heading the other way: the retrieved targets (centred on
    # their own box) are moved onto the car, turned, their front half becoming the crop's back half
    placed = dataclasses.replace(data, placement=np.broadcast_to(
        plane_placement(np.array([0.0, -0.1, np.pi]), np.ones(3)), data.placement.shape))
    at_box, on_car = (r.make_batch(d, np.array([0, 1]), config, np.random.default_rng(1))
                      for r, d in ((recipe, data), (recipe, placed)))
    for a, b in ((at_box.whole, on_car.whole), (at_box.half, on_car.half)):
        np.testing.assert_allclose(b[..., 1].numpy()[a[..., 1].numpy() != 0].mean(),
                                   -0.1 - a[..., 1].numpy()[a[..., 1].numpy() != 0].mean(), atol=1e-5)
    # the crop's front slot holds the entry's back half, turned to the front
    np.testing.assert_allclose(on_car.half[:, 0, :, 0].numpy(), -at_box.half[:, 1, :, 0].numpy(), atol=1e-5)
    assert (on_car.half[:, 0][on_car.half_mask[:, 0]][:, 0] >= -1e-6).all()
    batch = next(recipe.batches(data, 2, config, np.random.default_rng(0)))
    # a car whose plane is 0.1 (canonical units) left of the box's and turned 0.1 rad; its halves seen
    # from the +y flank only (what retrieval hands a +y input)
    rng = np.random.default_rng(3)
    car, _ = ellipsoid_surface(4000, ELLIPSOID, rng)
    yaw, shift = 0.1, np.array([0.0, -0.1])
    c, s = np.cos(yaw), np.sin(yaw)
    in_box = car.copy()
    in_box[:, :2] = car[:, :2] @ np.array([[c, s], [-s, c]]) + shift
    seen = car[:, 1] > 0.02

    def halves(mask: np.ndarray) -> torch.Tensor:
        pts = in_box[mask]
        front, back = pts[pts[:, 0] >= 0], pts[pts[:, 0] < 0]
        n = min(len(front), len(back), 256)
        return torch.from_numpy(np.stack([front[:n], back[:n]]).astype(np.float32))[None].repeat(2, 1, 1, 1)

    seen_halves, whole_halves = halves(seen), halves(np.ones(len(car), bool))
    batch.half, batch.half_mask = seen_halves, torch.ones(seen_halves.shape[:3], dtype=torch.bool)
    label = torch.from_numpy(plane_reflection(np.array([*shift, yaw]), np.ones(3)))[None].repeat(2, 1, 1)
    detailed = torch.from_numpy(in_box.astype(np.float32))[None].repeat(2, 1, 1)

    def partial(coarse: torch.Tensor, reflection: torch.Tensor | None, **options) -> float:
        batch.reflection = reflection
        return _recipe(tmp_path, **options).loss(_FixedOutput(detailed, coarse), batch)[1]["partial"]

    # without mirrored halves the seen flank alone is the better coarse output: the lean is taught
    assert partial(seen_halves, None) < partial(whole_halves, None)
    # mirrored across the labelled plane, the whole car is the better one
    on_label = dict(mirror_halves=True, mirror_plane="label")
    assert partial(whole_halves, label, **on_label) < partial(seen_halves, label, **on_label)
    # across the box's plane the mirrored flank misses the car by the box's error
    assert partial(whole_halves, label, **on_label) < partial(whole_halves, None, mirror_halves=True) - 0.005
    # the symmetry term follows the same plane (all 4000 points: no subset's sampling gap)
    symmetric = _recipe(tmp_path, symmetry_weight=1.0, detail_loss_points=0)
    batch.reflection = label
    about_label = symmetric.loss(_FixedOutput(detailed, whole_halves), batch)[1]["symmetry"]
    batch.reflection = None
    about_box = symmetric.loss(_FixedOutput(detailed, whole_halves), batch)[1]["symmetry"]
    assert about_label < 0.5 * about_box
    with pytest.raises(ConfigError, match="mirror_plane"):
        training_recipe(mirror_plane="car")
