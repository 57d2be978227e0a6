"""AML: voxel grids, ray-cast free space, reference SDFs, marching cubes, the VAE and the frozen decoder."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pcc_ros.errors import CheckpointError, ConfigError
from pcc_ros.geometry.partitions import grid_bounds, voxelize
from pcc_ros.geometry.voxels import (
    AML_GRID,
    BOX_GRID,
    GridSpec,
    estimate_origin,
    observation_grids,
    occupancy_grid,
    ray_voxels,
    reference_grids,
)
from pcc_ros.models.aml import (
    AML,
    DEFAULT_ASPECT,
    AMLRecipe,
    ObservationBatch,
    PriorBatch,
    ReferenceSet,
    augment_grids,
    depth_to_space,
    marching_cubes_batch,
    observed_nll,
    sample_meshes,
    space_to_depth,
)
from pcc_ros.models.base import SceneContext
from pcc_ros.models.checkpoint import load_checkpoint
from pcc_ros.types import Boxes


def _centre(h: int, l: int, w: int) -> np.ndarray:  # noqa: E741 - the grid's own axis names
    return AML_GRID.from_hlw(np.array([h, l, w], dtype=np.float64))


# --------------------------------------------------------------------------- grids


def test_grid_axes_are_height_length_width():
    assert AML_GRID.resolution == (24, 54, 24)
    # front-left-top corner voxel holds a point near canonical (+0.59, +0.29, +0.29)
    occ = occupancy_grid(np.array([[0.59, 0.29, 0.29], [-0.59, -0.29, -0.29], [5.0, 0.0, 0.0]]))
    assert occ.sum() == 2  # the point outside the grid is ignored
    assert occ[23, 53, 23] and occ[0, 0, 0]
    np.testing.assert_allclose(_centre(0, 0, 0), np.array([-0.6, -0.3, -0.3]) + AML_GRID.voxel_size / 2)
    np.testing.assert_allclose(AML_GRID.voxel_size, [1.2 / 54, 0.025, 0.025])
    # a point in voxel (h=5, l=30, w=7)
    occ = occupancy_grid(_centre(5, 30, 7)[None])
    assert np.argwhere(occ).tolist() == [[5, 30, 7]]


def test_free_space_along_an_axis_parallel_ray():
    point = _centre(10, 40, 12)
    origin = point - np.array([3.0, 0.0, 0.0])  # behind the grid, same row
    occupied, free = observation_grids([point[None]], origin[None], stop=1.0)
    assert np.argwhere(occupied[0]).tolist() == [[10, 40, 12]]
    # the ray enters at the rear face and stops one voxel short of the point's voxel centre
    assert sorted(np.argwhere(free[0])[:, 1].tolist()) == list(range(0, 40))
    assert (np.argwhere(free[0])[:, [0, 2]] == [10, 12]).all()
    # everything else is unobserved
    assert occupied.sum() + free.sum() == 41


def test_free_space_diagonal_ray_in_a_plane():
    # A ray in the z = const plane at 45 degrees in voxel units visits a staircase.
    spec = GridSpec(resolution=(4, 10, 10), lower=(0.0, 0.0, 0.0), upper=(10.0, 10.0, 4.0))
    o = np.array([[0.5, 0.25, 1.5]])
    e = np.array([[6.5, 6.25, 1.5]])
    free = ray_voxels(o, e, np.zeros(1, np.int64), 1, spec)[0]
    cells = {tuple(c) for c in np.argwhere(free)}
    expected = {(1, i, i) for i in range(7)} | {(1, i + 1, i) for i in range(6)}
    assert cells == expected


def _brute_force(o: np.ndarray, e: np.ndarray, spec: GridSpec, step: float) -> set[tuple[int, int, int]]:
    """Walk the segment in tiny steps (voxel coordinates) and collect (h, l, w) cells."""
    n = int(np.ceil(np.linalg.norm(e - o) / step)) + 1
    t = np.linspace(0.0, 1.0, n)
    p = np.floor(o + t[:, None] * (e - o)).astype(int)
    dims = spec.dims_xyz
    p = p[((p >= 0) & (p < dims)).all(1)]
    return {(int(c[2]), int(c[0]), int(c[1])) for c in p}


def _chord(o: np.ndarray, e: np.ndarray, cell: tuple[int, int, int]) -> float:
    """Length of the segment inside one voxel (voxel coordinates)."""
    lo = np.array([cell[1], cell[2], cell[0]], dtype=float)
    d = e - o
    with np.errstate(divide="ignore", invalid="ignore"):
        ta, tb = (lo - o) / d, (lo + 1 - o) / d
    t0 = np.nanmax(np.where(d != 0, np.minimum(ta, tb), -np.inf))
    t1 = np.nanmin(np.where(d != 0, np.maximum(ta, tb), np.inf))
    t0, t1 = max(t0, 0.0), min(t1, 1.0)
    return max(t1 - t0, 0.0) * float(np.linalg.norm(d))


@pytest.mark.slow
def test_exact_traversal_matches_a_brute_force_ray_walk():
    rng = np.random.default_rng(3)
    spec = AML_GRID
    dims = spec.dims_xyz.astype(float)
    origins = np.c_[rng.uniform(-40, 90, 60), rng.uniform(-30, 50, 60), rng.uniform(-5, 40, 60)]
    ends = rng.uniform(0, 1, (60, 3)) * dims
    inst = rng.integers(0, 3, 60)
    grids = ray_voxels(origins, ends, inst, 3, spec)
    step = 1e-3
    for r in range(60):  # a test: brute force per ray
        exact = {tuple(c) for c in np.argwhere(grids[inst[r]])}
        brute = _brute_force(origins[r], ends[r], spec, step)
        assert brute <= exact
        # voxels of other rays of the same grid aside, the extra ones are only grazed
        mine = {c for c in exact if _chord(origins[r], ends[r], c) > 0}
        assert all(_chord(origins[r], ends[r], c) < 4 * step for c in mine - brute)


def test_partitions_voxelize_agrees_with_the_brute_force_walk():
    """The voxeliser in geometry/partitions.py (step-sampled rays): every free voxel it
    marks is truly crossed, and every voxel crossed by more than its step is marked."""
    rng = np.random.default_rng(5)
    size = np.array([4.0, 1.7, 1.5])
    lower, vox = grid_bounds(size)
    spec = GridSpec(resolution=(24, 54, 24), lower=tuple(lower), upper=tuple(lower + vox * [54, 24, 24]))
    pts = rng.uniform(-0.45, 0.45, (40, 3)) * [1.0, 0.4, 0.35]
    origin = np.array([1.5, 3.0, 0.3])
    grid = voxelize(pts, origin, size, step=0.5, stop=1.0)
    g, o = spec.to_voxel(pts), spec.to_voxel(origin)
    crossed: set = set()
    long_chords: set = set()
    for p in g:  # per ray: brute force
        end = o + (p - o) * (1 - 1.0 / np.linalg.norm(p - o))
        cells = _brute_force(o, end, spec, 1e-3)
        crossed |= cells
        long_chords |= {c for c in cells if _chord(o, end, c) > 0.5 + 1e-6}
    marked = {tuple(c) for c in np.argwhere(grid.free)}
    occupied = {tuple(c) for c in np.argwhere(grid.occupied)}
    assert marked <= crossed
    assert long_chords - occupied <= marked
    # and the exact traversal gives the brute-force set
    _, exact = observation_grids([pts], origin[None], spec, stop=1.0)
    assert {tuple(c) for c in np.argwhere(exact[0])} >= (long_chords - occupied)


def test_batched_observations_equal_one_at_a_time():
    rng = np.random.default_rng(0)
    clouds = [rng.uniform(-0.4, 0.4, (n, 3)) * [1, 0.5, 0.4] for n in (30, 200, 5)]
    origins = np.array([[2.0, 3.0, 0.3], [-3.0, 1.0, 0.2], [0.0, -4.0, 0.5]])
    occ, free = observation_grids(clouds, origins)
    assert not (occ & free).any()
    for i in range(3):
        o1, f1 = observation_grids([clouds[i]], origins[i : i + 1])
        np.testing.assert_array_equal(o1[0], occ[i])
        np.testing.assert_array_equal(f1[0], free[i])


def test_estimated_origin_lies_on_the_visible_side():
    rng = np.random.default_rng(0)
    # the +y side and top of a car seen from the left
    pts = np.c_[rng.uniform(-0.5, 0.5, 300), np.full(300, 0.2), rng.uniform(-0.18, 0.18, 300)]
    pts = np.r_[pts, np.c_[rng.uniform(-0.5, 0.5, 100), rng.uniform(-0.2, 0.2, 100), np.full(100, 0.18)]]
    origin = estimate_origin(pts)
    assert origin[1] > 3.0 and np.degrees(np.arctan2(abs(origin[0]), origin[1])) < 15


def _sphere_surface(radius: float, n: int, centre=(0.0, 0.0, 0.0), seed: int = 0) -> np.ndarray:
    v = np.random.default_rng(seed).normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True) * radius + np.asarray(centre)


def test_reference_grids_of_a_sphere():
    r = 0.2
    occ, sdf = reference_grids(_sphere_surface(r, 30000))
    c = AML_GRID.centers()
    dist = np.linalg.norm(c, axis=-1)
    margin = AML_GRID.voxel_size.max()
    assert occ[dist < r - margin].all() and not occ[dist > r + margin].any()
    assert (sdf[dist < r - margin] < 0).all() and (sdf[dist > r + margin] > 0).all()
    true_sdf = np.clip((dist - r) / AML_GRID.mean_voxel, -3, 3)
    err = np.abs(sdf - true_sdf)  # voxel units
    assert err.max() < 0.5  # worst: a surface voxel's sign (its centre within ~0.25 voxel of the surface)
    assert err[np.abs(true_sdf) < 3].mean() < 0.1


# --------------------------------------------------------------------------- meshes


def _sphere_sdf(radius: float, centre=(0.0, 0.0, 0.0)) -> np.ndarray:
    d = np.linalg.norm(AML_GRID.centers() - np.asarray(centre), axis=-1)
    return ((d - radius) / AML_GRID.mean_voxel).astype(np.float32)


def test_marching_cubes_is_watertight_on_a_sphere():
    empty = np.full(AML_GRID.resolution, 2.0, np.float32)
    sdfs = np.stack([_sphere_sdf(0.2), _sphere_sdf(0.1, (0.3, 0.1, 0.0)), empty])
    meshes = marching_cubes_batch(sdfs)
    assert len(meshes[2][1]) == 0  # no surface
    for (verts, faces), radius, centre in zip(meshes[:2], (0.2, 0.1), ((0, 0, 0), (0.3, 0.1, 0.0))):
        assert len(faces) > 100
        edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
        _, counts = np.unique(edges, axis=0, return_counts=True)
        assert (counts == 2).all()  # closed 2-manifold: every edge has exactly two faces
        assert len(verts) - len(counts) + len(faces) == 2  # Euler characteristic of a sphere
        assert np.abs(np.linalg.norm(verts - centre, axis=1) - radius).max() < 0.012
    # a sphere cut by the grid border is still closed (the border layer is outside)
    verts, faces = marching_cubes_batch(_sphere_sdf(0.2, (0.55, 0.0, 0.0))[None])[0]
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    assert (np.unique(edges, axis=0, return_counts=True)[1] == 2).all()


def test_surface_sampling_is_uniform_and_seeded():
    meshes = marching_cubes_batch(np.stack([_sphere_sdf(0.2), _sphere_sdf(0.15)]))
    a = sample_meshes(meshes, 4000, [1, 2])
    b = sample_meshes(meshes, 4000, [1, 2])
    np.testing.assert_array_equal(a[0], b[0])
    assert np.abs(np.linalg.norm(a[0], axis=1) - 0.2).max() < 0.012
    assert np.abs(np.linalg.norm(a[1], axis=1) - 0.15).max() < 0.012
    # uniform by area: the hemispheres get half each
    assert 0.45 < (a[0][:, 2] > 0).mean() < 0.55
    assert sample_meshes([(np.zeros((0, 3)), np.zeros((0, 3), np.int64))], 10, [0])[0].shape == (0, 3)


# --------------------------------------------------------------------------- network


def test_space_to_depth_round_trip():
    x = torch.randn(2, 3, 24, 56, 24)
    np.testing.assert_array_equal(depth_to_space(space_to_depth(x)).numpy(), x.numpy())


def test_augmentation_identity_and_one_voxel_shift():
    rng = np.random.default_rng(0)
    occ = torch.zeros(1, *AML_GRID.resolution)
    occ[0, 10:14, 20:30, 8:16] = 1
    sdf = torch.randn(1, *AML_GRID.resolution)
    o, s = augment_grids(occ, sdf, rng, rotation_deg=0, scale=0, shift_voxels=0)
    np.testing.assert_array_equal(o.numpy(), occ.numpy())
    np.testing.assert_allclose(s.numpy(), sdf.numpy(), atol=1e-4)
    # rotation by a small angle keeps the volume
    o, _ = augment_grids(occ, sdf, rng, rotation_deg=4, scale=0, shift_voxels=0)
    assert abs(float(o.sum()) - float(occ.sum())) / float(occ.sum()) < 0.15


def test_observed_nll_only_counts_observed_voxels():
    decoded = torch.randn(2, 2, *AML_GRID.resolution)
    occupied = torch.zeros(2, *AML_GRID.resolution, dtype=torch.bool)
    free = torch.zeros_like(occupied)
    assert observed_nll(decoded, occupied, free, -2.0).abs().max() == 0
    occupied[0, 5, 5, 5] = True
    free[1, 6, 6, 6] = True
    nll = observed_nll(decoded, occupied, free, -2.0)
    assert nll[0] > 0 and nll[1] > 0
    # an occupied voxel predicted strongly inside (logit +, sdf -) costs little
    decoded[0, 0, 5, 5, 5], decoded[0, 1, 5, 5, 5] = 10.0, -3.0
    assert observed_nll(decoded, occupied, free, -2.0)[0] < 1e-3


def _toy_references(count: int, seed: int = 0) -> ReferenceSet:
    """Boxy 'cars' of random proportions as reference shapes (sampled surfaces -> grids)."""
    rng = np.random.default_rng(seed)
    occ, sdf = [], []
    for _ in range(count):
        half = np.array([0.5, rng.uniform(0.15, 0.22), rng.uniform(0.12, 0.2)])
        o = np.abs(AML_GRID.centers()) <= half
        inside = o.all(-1)
        d = np.max(np.abs(AML_GRID.centers()) - half, axis=-1) / AML_GRID.mean_voxel
        occ.append(inside)
        sdf.append(np.clip(d, -3, 3).astype(np.float32))
    return ReferenceSet(np.stack(occ), np.stack(sdf), [str(i) for i in range(count)])


@pytest.mark.slow
def test_vae_loss_decreases():
    torch.manual_seed(0)
    recipe = AMLRecipe(stage="prior", augment=False)
    completer = recipe.build_completer("cpu")
    net = completer.model.train()
    data = _toy_references(8)
    batches = recipe.batches(data, 4, completer.config, np.random.default_rng(0))
    opt = torch.optim.Adam(net.parameters(), lr=3e-3)
    losses = []
    for _ in range(30):
        loss, stats = recipe.loss(net, next(batches))
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(stats["loss"])
    assert np.mean(losses[-5:]) < 0.75 * np.mean(losses[:5])


@pytest.mark.slow
def test_frozen_decoder_stays_frozen_while_the_encoder_trains(tmp_path):
    torch.manual_seed(0)
    prior = AML(device="cpu")
    prior.save(tmp_path / "prior.safetensors", training={"stage": "prior"})
    recipe = AMLRecipe(stage="encoder", prior=str(tmp_path / "prior.safetensors"), lam=1.0)
    completer = recipe.build_completer("cpu")
    net = completer.model
    net.train()
    assert not net.decoder.training and net.encoder.training
    decoder_before = {k: v.clone() for k, v in net.decoder.state_dict().items()}
    for k, v in decoder_before.items():  # the prior's decoder was loaded
        torch.testing.assert_close(v, prior.model.decoder.state_dict()[k])
    encoder_before = {k: v.clone() for k, v in net.encoder.state_dict().items()}
    rng = np.random.default_rng(0)
    clouds = [rng.uniform(-0.4, 0.4, (150, 3)) * [1, 0.5, 0.4] for _ in range(4)]
    occupied, free = observation_grids(clouds, np.tile([[2.0, 3.0, 0.3]], (4, 1)))
    batch = ObservationBatch(torch.from_numpy(occupied), torch.from_numpy(free))
    opt = torch.optim.Adam([p for p in net.parameters() if p.requires_grad], lr=1e-2)
    for _ in range(3):
        loss, _ = recipe.loss(net, batch)
        opt.zero_grad()
        loss.backward()
        opt.step()
    for k, v in net.decoder.state_dict().items():  # weights and batch-norm statistics
        torch.testing.assert_close(v, decoder_before[k])
    assert any(not torch.equal(v, encoder_before[k]) for k, v in net.encoder.state_dict().items())
    assert all(p.grad is None for p in net.decoder.parameters())


def test_prior_batches_and_loss_shapes():
    recipe = AMLRecipe(stage="prior")
    completer = recipe.build_completer("cpu")
    batch = next(recipe.batches(_toy_references(3), 2, completer.config, np.random.default_rng(0)))
    assert isinstance(batch, PriorBatch) and batch.occupancy.shape == (2, *AML_GRID.resolution)
    loss, stats = recipe.loss(completer.model.train(), batch)
    assert torch.isfinite(loss) and {"nll", "kl"} <= set(stats)


# --------------------------------------------------------------------------- completer


def test_completer_contract_and_checkpoint(tmp_path):
    from pcc_ros.models import load_completer

    torch.manual_seed(0)
    aml = AML(device="cpu")
    aml.lam = 3.5
    path = aml.save(tmp_path / "aml.safetensors")
    loaded = load_completer("aml", path, device="cpu")
    assert loaded.lam == 3.5
    ml = load_completer("aml_ml", path, device="cpu")  # the ML baseline reads AML's checkpoint
    assert ml.inference == "ml" and ml.lam == 3.5
    ml.ml_steps = 3  # the optimisation runs; its length does not matter here
    rng = np.random.default_rng(0)
    # make the decoder output a fixed SDF by zeroing its last layer and biasing it
    with torch.no_grad():
        for m in (loaded, ml):
            out = m.model.decoder.out
            out.weight.zero_()
            out.bias.zero_()
            out.bias[8:] = -1.0  # SDF channel: -1 everywhere -> no zero crossing inside the grid...
    clouds = [rng.uniform(-0.4, 0.4, (n, 3)).astype(np.float32) * [1, 0.5, 0.4] for n in (20, 300)]
    res = loaded.complete(clouds)
    # ...so the border layer closes it: the surface is the grid box (halfway to the outside layer),
    # in the box frame, stretched by the default box aspect when no box (context) is given
    assert all(r.shape == (2048, 3) and np.isfinite(r).all() for r in res)
    assert np.abs(res[0]).max(axis=0) == pytest.approx(np.multiply(BOX_GRID.upper, DEFAULT_ASPECT), abs=1e-4)
    np.testing.assert_array_equal(loaded.complete(clouds[1:])[0], res[1])  # batch-independent
    assert all(r.shape == (2048, 3) for r in ml.complete(clouds))
    # with a box the completion takes the box's proportions: a tall, narrow 4 x 1.6 x 2.4 m box
    box = Boxes(np.array([[10.0, 0.0, 0.0]]), np.array([[4.0, 1.6, 2.4]]), np.array([0.3]), np.array(["Car"], object))
    ctx = SceneContext(box=box, neighbour_boxes=box[np.array([], int)])
    tall = loaded.complete(clouds[:1], [ctx])[0]
    assert np.abs(tall).max(axis=0) == pytest.approx([0.6, 0.6 * 0.4, 0.6 * 0.6], abs=1e-4)


def test_latent_whitening_keeps_the_decoder_function():
    from pcc_ros.models.aml import AMLNet, whiten_latent

    torch.manual_seed(0)
    net = AMLNet(10, [8, 16, 32]).eval()
    rng = np.random.default_rng(0)  # varied grids, so the codes vary in all ten directions
    refs = ReferenceSet(rng.random((40, *AML_GRID.resolution)) < 0.3,
                        rng.normal(0, 1.5, (40, *AML_GRID.resolution)).astype(np.float32), [])
    x = torch.stack([torch.from_numpy(refs.occupancy.astype(np.float32)), torch.from_numpy(refs.sdf) / 3.0], 1)
    with torch.no_grad():
        net.prior_encoder.fc.weight.mul_(1e3)  # an untrained net's codes hardly vary: spread them
        mu_before = net.prior_encoder(x)[:, :10]
        decoded_before = net.decoder(mu_before)
    whiten_latent(net, refs, 3.0)
    with torch.no_grad():
        mu_after = net.prior_encoder(x)[:, :10]
        decoded_after = net.decoder(mu_after)
    # the same shapes come out; their codes are now zero-mean with unit covariance
    torch.testing.assert_close(decoded_after, decoded_before, atol=2e-3, rtol=1e-3)
    assert mu_after.mean(0).abs().max() < 1e-3
    cov = torch.cov(mu_after.T.double())
    torch.testing.assert_close(cov, torch.eye(10, dtype=torch.float64), atol=2e-2, rtol=0)


# --------------------------------------------------------------------------- box frame (issue 18)


def test_box_frame_maps_every_box_to_the_unit_cube():
    from pcc_ros.geometry.voxels import box_aspect, from_box_frame, to_box_frame
    from pcc_ros.models.aml import shape_to_grid_frame

    aspect = box_aspect(np.array([4.4, 1.8, 1.5]))
    np.testing.assert_allclose(aspect, [1.0, 1.8 / 4.4, 1.5 / 4.4])
    corner = np.array([[0.5, 0.9 / 4.4, 0.75 / 4.4]])  # the box's front-left-top corner, canonical
    np.testing.assert_allclose(to_box_frame(corner, aspect), [[0.5, 0.5, 0.5]])
    np.testing.assert_allclose(from_box_frame(to_box_frame(corner, aspect), aspect), corner)
    # a reference shape fills the box frame's cube whatever its proportions (SynthCars: box = bounds)
    rng = np.random.default_rng(0)
    van = rng.uniform(-1, 1, (500, 3)) * [0.5, 0.2, 0.23] + [0.0, 0.0, 0.01]
    cube = shape_to_grid_frame(van, "box")
    np.testing.assert_allclose(cube.min(0), -0.5, atol=1e-9)
    np.testing.assert_allclose(cube.max(0), 0.5, atol=1e-9)
    np.testing.assert_array_equal(shape_to_grid_frame(van, "canonical"), van)
    with pytest.raises(Exception, match="positive"):
        box_aspect(np.array([4.0, 0.0, 1.5]))


def test_fused_surface_sampling_equals_meshes_then_sampling():
    from pcc_ros.geometry.voxels import from_box_frame
    from pcc_ros.models.aml import surface_samples

    sdfs = np.stack([_sphere_sdf(0.2), np.full(AML_GRID.resolution, 2.0, np.float32), _sphere_sdf(0.15, (0.2, 0, 0))])
    aspects = np.array([[1.0, 0.4, 0.35], [1.0, 0.5, 0.5], [1.0, 0.3, 0.45]])
    fused = surface_samples(sdfs, AML_GRID, aspects, 1000, [3, 4, 5])
    meshes = [(from_box_frame(v, a), f) for (v, f), a in zip(marching_cubes_batch(sdfs, AML_GRID), aspects)]
    split = sample_meshes(meshes, 1000, [3, 4, 5])
    assert len(fused[1]) == 0 and len(split[1]) == 0  # no surface
    for a, b in zip(fused, split):
        np.testing.assert_allclose(a, b, atol=1e-6)
    # the sphere, stretched by its aspect: an ellipsoid with semi-axes 0.2 * aspect
    assert np.abs(np.linalg.norm(fused[0] / (0.2 * aspects[0]), axis=1) - 1).max() < 0.08


def test_box_jitter_off_gives_the_completer_observation(tmp_path):
    from pcc_ros.models.aml import Observations

    rng = np.random.default_rng(1)
    clouds = [(rng.uniform(-0.4, 0.4, (80, 3)) * [1, 0.5, 0.4]).astype(np.float32) for _ in range(3)]
    origins = np.array([[2.0, 3.0, 0.3], [-3.0, 1.0, 0.2], [0.0, -4.0, 0.5]])
    aspects = np.array([[1.0, 0.4, 0.35], [1.0, 0.45, 0.5], [1.0, 0.38, 0.3]])
    data = Observations(clouds, origins, {}, aspects)
    recipe = AMLRecipe(stage="prior", augment=False)
    aml = AML(device="cpu")
    batch = recipe.observation_batch(data, np.arange(3), aml.config, rng)
    expected = aml.observe_frame(clouds, origins, aspects)
    torch.testing.assert_close(batch.grids(), expected)
    jittered = AMLRecipe(stage="prior", augment=True, box_jitter=0.1).observation_batch(
        data, np.arange(3), aml.config, np.random.default_rng(0))
    assert not torch.equal(jittered.occupied, batch.occupied)
    assert jittered.occupied.flatten(1).sum(1).tolist() != [0, 0, 0]


def test_consistency_pairs_add_the_code_gap_to_the_encoder_loss():
    from pcc_ros.models.aml import Observations

    rng = np.random.default_rng(3)
    clouds = [(rng.uniform(-0.4, 0.4, (80, 3)) * [1, 0.5, 0.4]).astype(np.float32) for _ in range(4)]
    data = Observations(clouds, np.tile([[2.0, 3.0, 0.3]], (4, 1)), {}, np.tile([[1.0, 0.4, 0.35]], (4, 1)),
                        np.array([1, 0, 3, 2]))
    torch.manual_seed(0)
    aml = AML(device="cpu")
    plain = AMLRecipe(stage="prior", augment=False, consistency=0.0)
    paired = AMLRecipe(stage="prior", augment=False, consistency=1e6)
    paired.stage = plain.stage = "encoder"  # without the prior checkpoint the encoder stage needs
    batch = next(paired.batches(data, 2, aml.config, np.random.default_rng(0)))
    assert batch.pairs == 2 and len(batch.occupied) == 4
    assert next(plain.batches(data, 2, aml.config, np.random.default_rng(0))).pairs == 0
    paired.completer = plain.completer = aml
    aml.model.eval()
    with torch.no_grad():  # codes that differ between the two frames
        aml.model.encoder.fc.weight.mul_(100.0)
    loss, stats = paired.loss(aml.model, batch)
    base, _ = plain.loss(aml.model, batch)
    observed = (batch.occupied | batch.free).flatten(1).sum(1).float().mean()
    assert stats["z_gap"] > 1e-3
    assert float((loss - base).detach()) == pytest.approx(1e6 * stats["z_gap"] / float(observed), rel=1e-3)
    with pytest.raises(ConfigError, match="consistency"):
        AMLRecipe(stage="prior", consistency=-1.0)


@pytest.mark.slow
def test_lambda_selection_scores_real_crops_by_held_out_points():
    from pcc_ros.models.aml import RealCrops, holdout_fidelity, ml_codes

    torch.manual_seed(0)
    aml = AML(device="cpu")
    rng = np.random.default_rng(2)
    clouds = [(rng.uniform(-0.45, 0.45, (60, 3)) * [1, 0.4, 0.3]).astype(np.float32) for _ in range(2)]
    crops = RealCrops(clouds, np.array([[2.0, 3.0, 0.3], [-3.0, 1.0, 0.2]]), np.array([[4.2, 1.7, 1.5]] * 2))
    table = holdout_fidelity(aml, crops, {str(lam): ml_codes(aml, 2, lam) for lam in (1.0, 100.0)}, holdout=0.3,
                             seed=0)
    assert set(table) == {"1.0", "100.0"}
    # metres: the held-out points of a ~4 m car lie within a few metres of any completion
    assert all(0 < v < 3.0 for v in table.values())
    assert holdout_fidelity(aml, crops, {"1.0": ml_codes(aml, 2, 1.0)}, holdout=0.3, seed=0)["1.0"] == table["1.0"]


def test_the_ml_baseline_is_found_by_name_in_a_fresh_process():
    import subprocess
    import sys

    # aml_ml lives beside aml in pcc_ros/models/aml/: the registry must find it without "aml" loaded first
    code = "from pcc_ros.models.registry import get_backend; print(get_backend('aml_ml').__name__)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "AMLMaximumLikelihood"


def test_decode_density_samples_denser_and_odd_boxes_are_clipped():
    from pcc_ros.models.aml import box_aspects

    torch.manual_seed(0)
    aml = AML(device="cpu", decode_density=2)
    assert aml.points_per_car() == round(2048 * 2.25)
    with torch.no_grad():  # a fixed SDF: the surface is the grid box (see the contract test)
        aml.model.decoder.out.weight.zero_()
        aml.model.decoder.out.bias.zero_()
        aml.model.decoder.out.bias[8:] = -1.0
    cloud = np.random.default_rng(0).uniform(-0.4, 0.4, (50, 3)).astype(np.float32) * [1, 0.4, 0.3]
    assert aml.complete([cloud])[0].shape == (4608, 3)
    # a box 3 x as wide as long (a detector's swapped axes) is clipped to 2 x the default aspect
    wide = Boxes(np.zeros((1, 3)), np.array([[1.8, 5.4, 1.5]]), np.zeros(1), np.array(["Car"], object))
    ctx = SceneContext(box=wide, neighbour_boxes=wide[np.array([], int)])
    np.testing.assert_allclose(box_aspects([ctx, None])[:, 1], [2 * DEFAULT_ASPECT[1], DEFAULT_ASPECT[1]])


def test_encoder_init_warm_starts_only_the_encoder(tmp_path):
    torch.manual_seed(0)
    AML(device="cpu").save(tmp_path / "prior.safetensors", training={"stage": "prior"})
    torch.manual_seed(1)
    other = AML(device="cpu")
    other.save(tmp_path / "other.safetensors", training={"stage": "encoder"})
    recipe = AMLRecipe(stage="encoder", prior=str(tmp_path / "prior.safetensors"), lam=1.0,
                       encoder_init=str(tmp_path / "other.safetensors"))
    net = recipe.build_completer("cpu").model
    for k, v in net.encoder.state_dict().items():
        torch.testing.assert_close(v, other.model.encoder.state_dict()[k])
    prior_state = load_checkpoint(tmp_path / "prior.safetensors")[0]
    for k, v in net.decoder.state_dict().items():
        torch.testing.assert_close(v, prior_state[f"decoder.{k}"])
    bad = AMLRecipe(stage="encoder", prior=str(tmp_path / "prior.safetensors"), lam=1.0,
                    encoder_init=str(tmp_path / "missing.safetensors"))
    with pytest.raises(CheckpointError, match=r"missing\.safetensors"):
        bad.build_completer("cpu")


def test_reference_grids_cache_follows_the_dataset_not_its_path(tmp_path, monkeypatch):
    """The voxelised shapes cached for one SynthCars root are reused for a copy of it elsewhere
    (a lent machine), and stored compactly (float16 SDF, read back as float32)."""
    import json
    import shutil

    from pcc_ros.models.aml import recipe as aml_recipe

    root = tmp_path / "synth"
    (root / "shapes" / "0000").mkdir(parents=True)
    (root / "meta.json").write_text(json.dumps({"splits": {"train": ["0000"], "test": []}}))
    rng = np.random.default_rng(0)
    for track in range(3):
        d = rng.normal(size=(4000, 3))
        surface = d / np.linalg.norm(d, axis=1, keepdims=True) * [0.45, 0.2, 0.17]
        np.save(root / "shapes" / "0000" / f"{track}.npy", surface.astype(np.float32))
    cache = tmp_path / "grids.npz"
    first = AMLRecipe(stage="prior", reference_cache=str(cache)).open_data(root)
    assert first.sdf.dtype == np.float32 and np.load(cache)["sdf"].dtype == np.float16
    shutil.copytree(root, tmp_path / "elsewhere")
    monkeypatch.setattr(aml_recipe, "synthcars_reference_shapes", lambda *a, **k: pytest.fail("recomputed"))
    again = AMLRecipe(stage="prior", reference_cache=str(cache)).open_data(tmp_path / "elsewhere")
    assert again.sdf.dtype == np.float32 and np.abs(again.sdf - first.sdf).max() < 5e-3
    np.testing.assert_array_equal(again.occupancy, first.occupancy)
