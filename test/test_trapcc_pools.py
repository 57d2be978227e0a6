"""TraPCC's ground-truth pools: admission by evenness, retrieval, caching and resuming, on
synthetic tracks with known answers (the tracks and the tiny network live in test_trapcc)."""

from __future__ import annotations

import numpy as np
import pytest
from test_trapcc import (  # noqa: F401  (train_cache: a fixture)
    BOXY,
    ELLIPSOID,
    VAN,
    _recipe,
    box_surface,
    ellipsoid_surface,
    track_frames,
    train_cache,
)

from pcc_ros.data.gt_pools import (
    PoolConfig,
    build_pools,
    load_or_assign,
    load_or_build_pools,
    otsu_threshold,
    retrieve,
    size_candidates,
)
from pcc_ros.data.instances import ExtractConfig, extract_instances


@pytest.fixture(scope="module")
def pool_cache(tmp_path_factory):
    """Two complete drive-bys (ellipsoid, box) and a parked car seen from one side only."""
    rng = np.random.default_rng(0)
    frames = (
        track_frames(ellipsoid_surface(6000, ELLIPSOID, rng), ELLIPSOID, "0000", "1", 16, seed=1)
        + track_frames(box_surface(6000, BOXY, rng), BOXY, "0001", "2", 16, seed=2)
        + track_frames(ellipsoid_surface(6000, VAN, rng), VAN, "0002", "3", 16, drive_by=False, seed=3)
    )
    cfg = ExtractConfig(val_fraction=0.0, test_fraction=0.0, ground_margin=0.0)
    return extract_instances(frames, tmp_path_factory.mktemp("pools") / "cache", cfg, progress=False)


def test_otsu_threshold_separates_two_groups():
    scores = np.array([0.0, 0.02, 0.05, 0.61, 0.7, 0.72, 0.8])
    t = otsu_threshold(scores)
    assert 0.05 < t < 0.61
    assert otsu_threshold(np.array([0.4, 0.4])) == 0.4  # one value: everything admitted
    assert otsu_threshold(np.array([0.1, 0.9])) == pytest.approx(0.5)


def test_pool_admission_by_evenness_with_data_driven_threshold(pool_cache):
    pools = build_pools([pool_cache], "train", PoolConfig(min_points=1024, min_half_points=300))
    assert pools.stats["whole"]["candidates"] == 3  # all three aggregates have >= 1024 points
    assert sorted(k.split(":")[1] for k in pools.whole.key) == ["0000/1", "0001/2"]  # the parked car fails
    t = pools.stats["whole"]["threshold"]
    assert pools.whole.score.min() >= t > 0.0
    # halves: both halves of both drive-bys; the one-sided parked car's halves fail too
    assert sorted(k.split(":")[1] for k in pools.front.key) == ["0000/1", "0001/2"]
    assert all((pools.front.cloud(e)[:, 0] >= 0).all() for e in range(len(pools.front)))
    assert all((pools.back.cloud(e)[:, 0] < 0).all() for e in range(len(pools.back)))
    assert pools.whole.count.min() >= 1024 // 2 and pools.whole.points.shape[1] == 2048
    # min_points is the paper's candidate rule: nothing reaches 10**6 points
    empty = build_pools([pool_cache], "train", PoolConfig(min_points=10**6, min_half_points=10**6))
    assert len(empty.whole) == 0 and empty.stats["whole"]["threshold"] is None


def test_retrieval_by_size_then_mcd(pool_cache):
    pools = build_pools([pool_cache], "train", PoolConfig(min_points=1024, min_half_points=300))
    keys = [k.split(":")[1] for k in pools.whole.key]
    ell, box = keys.index("0000/1"), keys.index("0001/2")
    rng = np.random.default_rng(5)
    pts, normals = ellipsoid_surface(3000, ELLIPSOID, rng)
    ell_query = pts[(normals[:, 1] < 0) & (rng.random(3000) < 0.2)]  # one side of an ellipsoid car
    pts, normals = box_surface(3000, BOXY, rng)
    box_query = pts[(normals[:, 1] < 0) & (rng.random(3000) < 0.2)]
    sizes = np.array([ELLIPSOID, ELLIPSOID, [4.05, 1.8, 1.5]])
    idx, mcd = retrieve(pools.whole, [ell_query, box_query, ell_query], sizes, k=8)
    assert idx.tolist() == [ell, box, ell]  # shape decides among similar sizes
    assert np.all(mcd >= 0) and mcd[0] < 1e-3
    # with a single size candidate, size decides: an ellipsoid query with the box's size gets the box
    idx1, _ = retrieve(pools.whole, [ell_query], np.array([BOXY]), k=1)
    assert idx1.tolist() == [box]
    assert size_candidates(np.array([BOXY]), pools.whole.size, 2)[0].tolist() == [box, ell]
    empty_idx, empty_mcd = retrieve(pools.whole, [np.zeros((0, 3))], np.array([BOXY]), k=2)
    assert empty_idx.tolist() == [-1] and np.isnan(empty_mcd[0])


def test_pools_and_assignments_are_cached_and_resumable(pool_cache, tmp_path, monkeypatch):
    import pcc_ros.data.gt_pools as gp

    cfg = PoolConfig(min_points=1024, min_half_points=300)
    pools, folder = load_or_build_pools([pool_cache], "train", tmp_path, cfg, progress=False)
    idx = pool_cache.indices("train")
    first = load_or_assign(pools, folder, pool_cache, idx, "train", 8, chunk=10, progress=False)
    assert (first["indices"] == idx).all() and (first["whole_index"] >= 0).all()
    assert not list(folder.glob("*.part*"))  # chunks merged
    # a rerun reuses both files: building or assigning again would fail here
    monkeypatch.setattr(gp, "build_pools", lambda *a, **k: pytest.fail("pools rebuilt"))
    monkeypatch.setattr(gp, "assign", lambda *a, **k: pytest.fail("retrieval recomputed"))
    again, folder2 = load_or_build_pools([pool_cache], "train", tmp_path, cfg, progress=False)
    assert folder2 == folder and len(again.whole) == len(pools.whole)
    second = load_or_assign(again, folder, pool_cache, idx, "train", 8, chunk=10, progress=False)
    assert all(np.array_equal(first[k], second[k], equal_nan=True) for k in first)
    # other options -> another fingerprint
    _, other = gp.pools_fingerprint([pool_cache], "train", cfg), gp.pools_fingerprint(
        [pool_cache], "train", PoolConfig(min_points=2048))
    assert other != gp.pools_fingerprint([pool_cache], "train", cfg)


def test_interrupted_assignment_resumes_from_chunks(pool_cache, tmp_path, monkeypatch):
    import pcc_ros.data.gt_pools as gp

    cfg = PoolConfig(min_points=1024, min_half_points=300)
    pools, folder = load_or_build_pools([pool_cache], "train", tmp_path, cfg, progress=False)
    idx = pool_cache.indices("train")
    real_assign = gp.assign
    calls = []

    def flaky(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real_assign(*args, **kwargs)

    monkeypatch.setattr(gp, "assign", flaky)
    with pytest.raises(KeyboardInterrupt):
        load_or_assign(pools, folder, pool_cache, idx, "train", 8, chunk=10, progress=False)
    assert len(list(folder.glob("*.part0000.npz"))) == 1
    calls.clear()
    monkeypatch.setattr(gp, "assign", real_assign)
    done = load_or_assign(pools, folder, pool_cache, idx, "train", 8, chunk=10, progress=False)
    assert len(done["indices"]) == len(idx)


def test_pools_from_other_caches(train_cache, pool_cache, tmp_path):  # noqa: F811  (a fixture)
    """pool_data: targets from other crops of the data (e.g. tight ones) than the inputs."""
    recipe = _recipe(tmp_path, pool_data=[str(pool_cache.root)])
    data = recipe.training_data(train_cache, "train", min_points=10)
    keys = set(data.pools.whole.key)
    assert keys and all(k.startswith("0:") for k in keys)
    assert recipe.data_summary()["pool_sources"] == [{"cache": str(pool_cache.root), "source": None,
                                                      "crop": {"boxes": "ground_truth", "margin": 0.0,
                                                               "ground_margin": 0.0, "min_points": 10}}]
    own = _recipe(tmp_path / "own").training_data(train_cache, "train", min_points=10)  # caches without a
    assert {k for k in own.pools.whole.key} != keys or not np.array_equal(  # source share a fingerprint
        data.pools.whole.points, own.pools.whole.points)


def _evenness_by_unique_rows(cloud, cell, center):
    """The paper's quadrant test written plainly (unique 2-D cells per view): the reference
    the 1-D cell keys of ``candidate_score`` must reproduce."""
    out = {}
    for name, u, v in (("side", 0, 2), ("front", 1, 2), ("top", 0, 1)):
        cells = np.unique(np.floor(cloud[:, [u, v]] / cell).astype(np.int64), axis=0)
        mid = (cells + 0.5) * cell
        counts = np.bincount((mid[:, 0] >= center[u]).astype(int) + 2 * (mid[:, 1] >= center[v]), minlength=4)
        out[name] = counts.min() / max(counts.max(), 1)
    return out


def test_fast_evenness_matches_the_plain_definition():
    from pcc_ros.data.gt_pools import candidate_score, thin

    rng = np.random.default_rng(4)
    cloud = ellipsoid_surface(4000, ELLIPSOID, rng)[0]
    cloud = cloud[(cloud[:, 1] < 0.1) | (rng.random(len(cloud)) < 0.3)]
    for part, cx in (("whole", 0.0), ("front", 0.25), ("back", -0.25)):
        score, views = candidate_score(cloud, 0.02, part)
        assert views == pytest.approx(_evenness_by_unique_rows(cloud, 0.02, (cx, 0.0, 0.0)))
        assert score == min(views.values())
    thinned = thin(cloud, 0.05)
    keys = np.floor(thinned / 0.05).astype(int)
    assert len(np.unique(keys, axis=0)) == len(thinned) == len(np.unique(np.floor(cloud / 0.05), axis=0))
