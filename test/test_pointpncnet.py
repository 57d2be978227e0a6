"""PointPnCNet: building blocks, the network, the completer and the training pieces."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from shapes import box_surface

from pcc_ros.data.instances import ExtractConfig, extract_instances
from pcc_ros.errors import CheckpointError, ConfigError
from pcc_ros.geometry.canonical import from_canonical
from pcc_ros.geometry.partitions import octant_masks
from pcc_ros.models import create, load_completer
from pcc_ros.models.base import resample_cloud
from pcc_ros.models.layers import FoldingDecoder, PCNEncoder, segment_max
from pcc_ros.models.losses import symmetry_chamfer, weighted_chamfer
from pcc_ros.models.pointpncnet import (
    NUM_REGIONS,
    PRESETS,
    PlaneView,
    PointPnCNet,
    TrainOptions,
    make_train_batch,
    pack,
    region_subsets,
    remove_regions,
    target_flags,
    training_recipe,
)
from pcc_ros.models.recipe import plane_reflection
from pcc_ros.types import Boxes, Sample


def car_like(rng: np.random.Generator, n: int) -> np.ndarray:
    """Points on the surface of a car-sized canonical box (x in [-0.5, 0.5])."""
    return box_surface(rng, n, [0.5, 0.2, 0.15]).astype(np.float32)


@pytest.fixture(scope="module")
def completer() -> PointPnCNet:
    torch.manual_seed(0)
    return create("pointpncnet", device="cpu")


# --------------------------------------------------------------------------- layers


def test_weighted_chamfer_matches_brute_force():
    rng = np.random.default_rng(1)
    target = rng.normal(size=(3, 7, 3)).astype(np.float32)
    mask = np.ones((3, 7), dtype=bool)
    mask[0, 4:] = False
    mask[2, :] = False  # an empty target row gives 0
    pred = rng.normal(size=(3, 5, 3)).astype(np.float32)
    beta = 0.25
    got = weighted_chamfer(torch.from_numpy(target), torch.from_numpy(mask), torch.from_numpy(pred), beta).numpy()
    for i in range(2):
        x = target[i][mask[i]]
        d = np.linalg.norm(x[:, None] - pred[i][None], axis=-1)
        expected = (1 - beta) * d.min(1).mean() + beta * d.min(0).mean()
        assert got[i] == pytest.approx(expected, rel=1e-4, abs=1e-5)
    assert got[2] == 0.0


def test_weighted_chamfer_gradient_is_that_of_the_min_formulation():
    rng = np.random.default_rng(2)
    target = torch.from_numpy(rng.normal(size=(2, 9, 3)).astype(np.float32))
    mask = torch.ones(2, 9, dtype=torch.bool)
    mask[1, 5:] = False
    pred = torch.from_numpy(rng.normal(size=(2, 6, 3)).astype(np.float32)).requires_grad_()
    weighted_chamfer(target, mask, pred, 0.25).sum().backward()
    ours = pred.grad.clone()
    pred.grad = None
    d = torch.cdist(pred, target)
    big = d.masked_fill(~mask[:, None, :], 1e9)
    x2y = (d.min(1).values * mask).sum(1) / mask.sum(1)
    ref = 0.75 * x2y + 0.25 * big.min(2).values.mean(1)
    ref.sum().backward()
    assert torch.allclose(ours, pred.grad, atol=1e-5)
    assert torch.isfinite(ours).all()


def test_segment_max_per_segment_and_empty_segments():
    feats = torch.tensor([[1.0, -5.0], [3.0, -7.0], [-2.0, -1.0], [0.5, 4.0]])
    seg = torch.tensor([0, 0, 2, 2])
    out = segment_max(feats, seg, 4)
    assert torch.equal(out, torch.tensor([[3.0, -5.0], [0.0, 0.0], [0.5, 4.0], [0.0, 0.0]]))


def test_split_layers_equal_the_published_concatenations():
    """The encoder's and folding decoder's split linear maps are exactly PCN's concatenations."""
    torch.manual_seed(0)
    enc = PCNEncoder([8, 16], [32, 12])
    pts = torch.randn(10, 3)
    seg = torch.tensor([0] * 4 + [1] * 6)
    out = enc(pts, seg, 2)
    # reference: concat(per-point feature, pooled feature) through one Linear with stacked weights
    w = torch.cat([enc.point_proj.weight, enc.segment_proj.weight], dim=1)
    ref = []
    for s in range(2):
        f = enc.mlp1(pts[seg == s])
        g = f.max(0).values.expand_as(f)
        h = torch.relu(torch.cat([f, g], 1) @ w.T + enc.point_proj.bias)
        ref.append(enc.mlp2(h).max(0).values)
    assert torch.allclose(out, torch.stack(ref), atol=1e-5)

    dec = FoldingDecoder(12, [16], num_coarse=5, grid_size=2, fold_widths=[10, 10], grid_scale=0.05)
    code = torch.randn(3, 12)
    coarse, fine = dec(code)
    assert coarse.shape == (3, 5, 3) and fine.shape == (3, 20, 3)
    w = torch.cat([dec.fold_grid.weight, dec.fold_point.weight, dec.fold_code.weight], dim=1)  # (10, 2+3+12)
    grid = dec.grid[None, None].expand(3, 5, 4, 2)
    feat = torch.cat([grid, coarse[:, :, None].expand(3, 5, 4, 3), code[:, None, None].expand(3, 5, 4, 12)], -1)
    ref = coarse[:, :, None] + dec.fold_mlp(torch.relu(feat @ w.T + dec.fold_code.bias))
    assert torch.allclose(fine, ref.reshape(3, 20, 3), atol=1e-5)


# --------------------------------------------------------------------------- network / completer


def test_output_sizes_of_both_presets():
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    clouds = [car_like(rng, 200), car_like(rng, 37)]
    small = create("pointpncnet", device="cpu")
    out = small.complete(clouds)
    assert [o.shape for o in out] == [(2048, 3), (2048, 3)]
    paper = create("pointpncnet", device="cpu", size="paper", batch_size=2)
    out = paper.complete(clouds)
    assert [o.shape for o in out] == [(8192, 3), (8192, 3)]  # 4096 global + 8 x 512 local
    assert paper.config["max_input_points"] == 3096
    assert sum(p.numel() for p in paper.model.parameters()) > 10 * sum(p.numel() for p in small.model.parameters())


def test_completion_independent_of_batch_and_of_duplicate_points(completer):
    rng = np.random.default_rng(3)
    a, b, c = car_like(rng, 150), car_like(rng, 600), car_like(rng, 40)
    alone = completer.complete([a])[0]
    batched = completer.complete([b, a, c])[1]
    np.testing.assert_allclose(alone, batched, atol=2e-5)
    # max-pooled encoders: duplicated real points change nothing (what padding by duplicates relies on)
    duplicated = completer.complete([np.concatenate([a, a[:70]])])[0]
    np.testing.assert_allclose(alone, duplicated, atol=2e-5)
    different = completer.complete([b])[0]
    assert np.abs(different - alone).max() > 1e-4


def test_large_clouds_capped_by_a_content_seeded_subset(completer):
    rng = np.random.default_rng(4)
    big = car_like(rng, 3000)
    cap = completer.config["max_input_points"]
    first = completer.complete([big])[0]
    np.testing.assert_array_equal(first, completer.complete([big])[0])
    np.testing.assert_allclose(first, completer.complete([resample_cloud(big, cap)])[0], atol=2e-5)


def test_region_presence_needs_min_points(completer):
    rng = np.random.default_rng(5)
    cloud = car_like(rng, 400)
    cloud = cloud[(cloud[:, 0] > 0.05) & (cloud[:, 1] > 0.05)]  # only the front-left quarter: 2 octants
    extra = np.array([[-0.3, -0.1, -0.1]] * 3, dtype=np.float32)  # 3 points in the rear-right-bottom octant
    packed = pack([np.concatenate([cloud, extra])], completer.config["region_overlap"])
    with torch.inference_mode():
        _, _, present = completer.model(packed.points, packed.segment, packed.regions, 1)
    counts = octant_masks(np.concatenate([cloud, extra])).sum(0)
    np.testing.assert_array_equal(present[0].numpy(), counts >= 4)
    assert present[0].sum() == 2


def test_config_errors():
    with pytest.raises(ConfigError, match="unknown size"):
        create("pointpncnet", device="cpu", size="huge")
    with pytest.raises(ConfigError, match="unknown option"):
        create("pointpncnet", device="cpu", widths=3)
    with pytest.raises(ConfigError, match="global embedding width"):
        create("pointpncnet", device="cpu", local_encoder_widths2=[32, 64])


def test_checkpoint_round_trip_and_corruption(completer, tmp_path):
    rng = np.random.default_rng(6)
    cloud = car_like(rng, 120)
    path = completer.save(tmp_path / "pnc.safetensors", training={"note": "test"})
    loaded = load_completer("pointpncnet", path, device="cpu")
    np.testing.assert_array_equal(loaded.complete([cloud])[0], completer.complete([cloud])[0])
    assert loaded.config == completer.config
    data = bytearray(path.read_bytes())
    data[-10] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(CheckpointError):
        load_completer("pointpncnet", path, device="cpu")


# --------------------------------------------------------------------------- training pieces


def test_remove_regions_drops_whole_octants_and_keeps_one():
    rng = np.random.default_rng(7)
    cloud = car_like(rng, 2000)
    regions = octant_masks(cloud, 0.005)
    kept, kept_regions = remove_regions(cloud, regions, 1.0, 4, rng)  # drop everything possible
    present_after = kept_regions.sum(0) >= 4
    assert present_after.sum() >= 1 and len(kept) < len(cloud)
    # every remaining point lies in no dropped octant: the dropped octants are empty now
    dropped = (regions.sum(0) >= 4) & ~present_after
    assert not kept_regions[:, dropped].any()
    same, _ = remove_regions(cloud, regions, 0.0, 4, rng)
    assert same is cloud
    dropped_counts = [len(remove_regions(cloud, regions, 0.2, 4, np.random.default_rng(s))[0]) for s in range(50)]
    assert min(dropped_counts) < len(cloud) and max(dropped_counts) == len(cloud)


def test_region_subsets_cap_each_octant():
    rng = np.random.default_rng(8)
    regions = octant_masks(car_like(rng, 500), 0.005)
    pairs, slot = region_subsets(regions, 10, rng)
    counts = np.bincount(pairs[:, 1], minlength=NUM_REGIONS)
    np.testing.assert_array_equal(counts, np.minimum(regions.sum(0), 10))
    assert regions[pairs[:, 0], pairs[:, 1]].all()
    assert (slot < 10).all() and len(np.unique(pairs[:, 1] * 100 + slot)) == len(slot)


def test_train_batch_uses_only_the_observed_views():
    rng = np.random.default_rng(9)
    views = [[car_like(rng, n) for n in (300, 80, 500)], [car_like(rng, 60)]]
    options = TrainOptions(loss_points=128, local_loss_points=16, views=2)
    batch = make_train_batch(views, PRESETS["default"], options, rng)
    assert batch.target.shape == (2, 2, 128, 3) and batch.local_target.shape == (2, 2, 8, 16, 3)
    np.testing.assert_array_equal(batch.view_mask.numpy(), [[True, True], [True, False]])
    for i, group in enumerate(views):
        pool = np.concatenate(group)
        for t, m in ((batch.target[i], batch.target_mask[i]), (batch.local_target[i], batch.local_mask[i])):
            pts = t[m].numpy()
            assert len(pts) > 0
            assert (np.abs(pts[:, None] - pool[None]).sum(-1).min(1) == 0).all()  # every target point observed
    # local targets sit in their octant
    lt, lm = batch.local_target.numpy(), batch.local_mask.numpy()
    for r in range(NUM_REGIONS):
        pts = lt[:, :, r][lm[:, :, r]]
        assert octant_masks(pts, 0.005)[:, r].all()
    # the input is one (possibly occluded) view of each group, nothing more
    seg = batch.inputs.segment.numpy()
    assert set(seg.tolist()) == {0, 1}
    assert (seg[:-1] <= seg[1:]).all()


def test_symmetry_options_mirror_the_targets_flip_groups_and_score_asymmetry():
    """mirror_targets joins each target view with its reflection (y -> -y); flip_prob reflects whole
    groups; symmetry_weight adds the asymmetry of the global output to the loss."""
    rng = np.random.default_rng(4)
    one_side = [[np.abs(car_like(rng, n)) * np.array([1, 1, 1], np.float32) for n in (300, 200)] for _ in range(2)]
    plain = make_train_batch(one_side, PRESETS["default"], TrainOptions(loss_points=4096, views=2, drop_prob=0.0), rng)
    assert (plain.target[plain.target_mask][:, 1] >= 0).all()  # the seen flank only
    mirrored = make_train_batch(one_side, PRESETS["default"],
                                TrainOptions(loss_points=4096, views=2, drop_prob=0.0, mirror_targets=True), rng)
    pts = mirrored.target[mirrored.target_mask].numpy()
    assert (pts[:, 1] < -0.01).mean() == pytest.approx(0.5, abs=0.05)  # the far flank is a target too
    assert mirrored.region_present.sum() > plain.region_present.sum()  # and so are its octants
    flipped = make_train_batch(one_side, PRESETS["default"],
                               TrainOptions(loss_points=4096, views=2, drop_prob=0.0, flip_prob=1.0), rng)
    assert (flipped.target[flipped.target_mask][:, 1] <= 0).all()
    assert (flipped.inputs.points.numpy()[:, 1] <= 0).all()
    torch.manual_seed(0)
    recipe = training_recipe("default", loss_points=128, local_loss_points=16, symmetry_weight=1.0)
    net = recipe.build_completer("cpu").model.train()
    _, stats = recipe.loss(net, plain)
    assert stats["symmetry"] > 0 and stats["loss"] > stats["global"] + stats["local"]
    assert "symmetry" not in training_recipe("default", loss_points=128).loss(net, plain)[1]


def _scene_frames(n_frames: int = 3) -> list[Sample]:
    """One car per frame with a ground plane under it and clutter just outside its box: what a
    node crop (margin, lower ground cut) holds and a tight crop does not."""
    rng = np.random.default_rng(5)
    size = np.array([4.4, 1.8, 1.5])
    frames = []
    for f in range(n_frames):
        center, yaw = np.array([6.0 + f, 3.0, -0.9]), 0.2 * f
        car = box_surface(rng, 1500, size / size[0] / 2 * 0.97)  # canonical, inside the box
        ground = np.c_[rng.uniform(-0.6, 0.6, (300, 2)), np.full(300, -size[2] / 2 / size[0] + 0.01)]
        side = np.c_[rng.uniform(-0.5, 0.5, 100), np.full(100, (size[1] / 2 + 0.05) / size[0]),
                     rng.uniform(-0.1, 0.1, 100)]  # 5 cm beside the flank: inside a 0.1 m margin only
        points = from_canonical(np.concatenate([car, ground, side]), center, yaw, size[0])
        boxes = Boxes([center], [size], [yaw], label=["Car"], track_id=["1"])
        frames.append(Sample(stamp_ns=f * 100_000_000, frame_id="velodyne",
                             points=np.c_[points, np.zeros(len(points))].astype(np.float32), ground_truth=boxes,
                             sequence="0000", index=f))
    return frames


def test_node_crop_inputs_with_tight_crop_targets(tmp_path):
    """target_margin: the input is the node's crop, the pseudo ground truth exactly the tight crop
    of the same observation (pcc extract's defaults), and held-out sources are refused."""
    frames = _scene_frames()
    split = {"val_fraction": 0.0, "test_fraction": 0.0}
    node = extract_instances(frames, tmp_path / "node", ExtractConfig(margin=0.1, ground_margin=0.05, **split),
                             source=tmp_path / "src" / "synth", progress=False)
    tight = extract_instances(frames, tmp_path / "tight", ExtractConfig(**split), progress=False)
    recipe = training_recipe(target_margin=0.0, target_ground_margin=0.1, held_out=[str(tmp_path / "held")])
    groups = recipe.training_data(node, "train")
    assert len(groups) == 1 and len(groups[0]) == len(frames) == len(tight)
    for i, view in enumerate(groups[0]):
        assert view.shape[1] == 4
        np.testing.assert_allclose(view[:, :3], node.points(i), atol=1e-6)  # the input: the whole node crop
        target = view[view[:, 3] > 0, :3]
        assert 0 < len(target) < len(view)  # ground and side clutter are not targets
        np.testing.assert_allclose(np.sort(target, axis=0), np.sort(tight.points(i), axis=0), atol=1e-5)
    batch = make_train_batch(groups, PRESETS["default"], TrainOptions(loss_points=4096, views=3, drop_prob=0.0),
                             np.random.default_rng(0))
    targets = batch.target[batch.target_mask].numpy()
    lowest = float(np.concatenate([tight.points(i) for i in range(len(tight))])[:, 2].min())
    assert targets[:, 2].min() >= lowest - 1e-6  # no ground return reached the targets ...
    assert batch.inputs.points.numpy()[:, 2].min() < lowest - 0.01  # ... while the input holds them
    summary = recipe.data_summary()
    assert summary["target_crop"] == {"margin": 0.0, "ground_margin": 0.1}
    assert summary["sources"][0]["crop"]["margin"] == 0.1 and summary["sources"][0]["observations"] == 3
    assert summary["held_out"]["sources"] == [str((tmp_path / "held").resolve())]
    # a crop that lacks the targets' points, a held-out source: clear errors, no training
    with pytest.raises(ConfigError, match="reaches outside the crop"):
        training_recipe(target_margin=0.0, target_ground_margin=0.1).training_data(
            extract_instances(frames, tmp_path / "low", ExtractConfig(ground_margin=0.2, **split), progress=False),
            "train")
    with pytest.raises(ConfigError, match=r"^pointpncnet: cache .*held out"):
        training_recipe(held_out=[str(tmp_path / "src")]).training_data(node, "train")
    # the flags are the crop's test: a point on the tight box's faces is in, 1 mm outside is out
    size = np.array([4.0, 2.0, 1.5])
    edge = np.array([[0.5, 0.25, 0.0], [0.0, 0.0, (-0.75 + 0.1) / 4], [0.50025, 0.0, 0.0],
                     [0.0, 0.0, (-0.75 + 0.099) / 4]])
    np.testing.assert_array_equal(target_flags(edge, size, 0.0, 0.1), [True, True, False, False])


@pytest.mark.slow
def test_a_few_steps_reduce_the_loss():
    torch.manual_seed(0)
    rng = np.random.default_rng(10)
    groups = [[car_like(rng, int(n)) for n in rng.integers(40, 300, 3)] for _ in range(8)]
    recipe = training_recipe("default", loss_points=128, local_loss_points=16)
    completer = recipe.build_completer("cpu")
    net = completer.model.train()
    optimizer = torch.optim.Adam(net.parameters(), lr=1e-3)
    batches = recipe.batches(groups, 8, completer.config, rng)
    losses = []
    for _ in range(40):
        loss, stats = recipe.loss(net, next(batches))
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(stats["loss"])
    assert np.mean(losses[-5:]) < 0.6 * np.mean(losses[:5])
    assert recipe.describe()["drop_prob"] == 0.2
    assert training_recipe("default", inpainting=False).describe()["drop_prob"] == 0.0


def test_shipped_checkpoint_completes_a_car():
    """The default weights load, were trained self-supervised, and fill in the hidden side."""
    from pcc_ros.models import default_checkpoint

    path = default_checkpoint("pointpncnet")
    assert path is not None and path.stat().st_size < 5 * 2**20
    pnc = load_completer("pointpncnet", device="cpu")
    training = pnc.checkpoint_config["training"]
    assert training["recipe"]["inpainting"] and training["split"] == "train"
    assert pnc.checkpoint_config["metrics"]["val_cd_l1"] < 0.05
    rng = np.random.default_rng(11)
    car = car_like(rng, 4000)
    seen = car[car[:, 1] > 0.1]  # only the left flank and the roof/bottom beside it
    out = pnc.complete([seen])[0]
    assert out.shape == (2048, 3) and np.isfinite(out).all()
    assert (out[:, 1] < -0.1).mean() > 0.1  # a real share of points on the unseen right side ...
    assert out[:, 1].min() < -0.15  # ... reaching out to where its flank is (y = -0.2)
    assert np.abs(out[:, 0]).max() < 0.8 and np.abs(out[:, 1]).max() < 0.5  # within a car-sized box


def test_label_mirror_plane_puts_the_mirrored_target_on_the_true_far_side():
    """A detector's box 0.1 (canonical units) to the car's left and turned 0.1 rad: the box-plane mirror
    lands the seen flank's reflection off the car, the labelled box's plane (``PlaneView``) on the
    true far flank, with the aspect scaling, through a flip, and in the symmetry term."""
    rng = np.random.default_rng(5)
    car = car_like(rng, 4000).astype(np.float64)  # the true car, symmetric about its own x-z plane
    yaw, shift = 0.1, np.array([0.0, -0.1])  # the car's plane in the detector box's frame
    c, s = np.cos(yaw), np.sin(yaw)
    in_box = car.copy()
    in_box[:, :2] = car[:, :2] @ np.array([[c, s], [-s, c]]) + shift
    seen, far = in_box[car[:, 1] > 0.05], in_box[car[:, 1] < -0.05]
    scales = np.array([1.0, 1.1, 0.9])
    view = PlaneView(seen.astype(np.float32) * scales.astype(np.float32),
                     plane_reflection(np.array([*shift, yaw]), scales))
    options = TrainOptions(loss_points=4096, views=1, drop_prob=0.0, mirror_targets=True)

    def far_half_error(batch) -> float:
        """Median distance of the mirrored half of the target to the true far flank (metres / length)."""
        pts = batch.target[batch.target_mask].numpy().astype(np.float64)
        if batch.inputs.points.numpy()[:, 1].mean() < 0:  # a flipped group: back to the box's frame
            pts[:, 1] *= -1
        pts = pts[len(pts) // 2:] / scales
        return float(np.median(np.sqrt(((pts[:, None] - far[None]) ** 2).sum(-1)).min(1)))

    labelled = make_train_batch([[view]], PRESETS["default"], options, rng)
    boxed = make_train_batch([[view.points]], PRESETS["default"], options, rng)
    assert far_half_error(labelled) < 0.01  # the reflection is the true far flank
    assert far_half_error(boxed) > 0.1  # the box's plane misses it by the box's error
    assert labelled.reflection is not None and boxed.reflection is None
    flips = make_train_batch([[view]], PRESETS["default"], TrainOptions(**{**options.__dict__, "flip_prob": 1.0}), rng)
    assert flips.inputs.points.numpy()[:, 1].mean() < 0  # flipped; its car plane flipped with it
    assert far_half_error(flips) < 0.01
    # the symmetry term vanishes for a car symmetric about its labelled plane, not about the box's
    whole = torch.from_numpy((in_box * scales).astype(np.float32))[None]
    refl = torch.from_numpy(view.reflection)[None]
    assert symmetry_chamfer(whole, refl) < 0.01 < symmetry_chamfer(whole)
    with pytest.raises(ConfigError):
        TrainOptions(mirror_plane="car")
