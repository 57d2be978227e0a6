"""Torch datasets over the instance cache: shapes, determinism, no ground-truth leakage."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from test_instances import make_track_frames

from pcc_ros.data.instance_datasets import InstanceDataset, MultiViewDataset, PoolDataset
from pcc_ros.data.instances import extract_instances, whole_gt_pool
from pcc_ros.errors import DataError


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    frames, _ = make_track_frames(n_frames=24)
    return extract_instances(frames, tmp_path_factory.mktemp("d") / "c", progress=False)


def test_instance_dataset(cache):
    split = str(cache.meta["split"][0])
    ds = InstanceDataset(cache, split, n_points=256, seed=3)
    assert len(ds) == 24
    item = ds[0]
    assert item["points"].shape == (256, 3) and item["points"].dtype == torch.float32
    assert set(item) == {"points", "origin", "num_points", "index"}  # no shape of any kind
    again = InstanceDataset(cache, split, n_points=256, seed=3)[0]
    assert torch.equal(item["points"], again["points"])
    ds.set_epoch(1)
    assert not torch.equal(ds[0]["points"], item["points"])
    # Every resampled point is an observed point of that instance.
    observed = {tuple(p) for p in np.asarray(cache.points(int(item["index"])))}
    assert all(tuple(p) in observed for p in item["points"].numpy())
    with pytest.raises(DataError):
        InstanceDataset(cache, split, min_points=10**6)


def test_multiview_and_pool_datasets(cache):
    split = str(cache.meta["split"][0])
    mv = MultiViewDataset(cache, split, views=4, group_size=20, n_points=128)
    assert len(mv) == 2  # 24 observations: a run of 20 and a run of 4 (>= views, kept)
    item = mv[0]
    assert item["views"].shape == (4, 128, 3) and len(set(item["indices"].tolist())) == 4
    loader = torch.utils.data.DataLoader(mv, batch_size=1)
    assert next(iter(loader))["views"].shape == (1, 4, 128, 3)
    pool = PoolDataset(whole_gt_pool(cache, split=None), n_points=512)
    assert pool[0]["points"].shape == (512, 3) and int(pool[0]["part"]) == 0
