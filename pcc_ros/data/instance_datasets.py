"""``torch.utils.data.Dataset`` views of an instance cache for training.

Separate from :mod:`pcc_ros.data.instances` so that ``pcc extract`` never imports torch.
None of these datasets can return a SynthCars ground-truth shape: they only read
:class:`~pcc_ros.data.instances.InstanceCache`, which has no access to them.

Determinism: each item's random choices come from ``numpy.random.default_rng((seed,
epoch, index))``, so an item is reproducible regardless of worker count or order;
call ``set_epoch`` to draw new resamplings each epoch.
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np
import torch
from torch.utils.data import Dataset

from pcc_ros.data.instances import InstanceCache, PoolEntry, multiview_groups, sample_views
from pcc_ros.errors import DataError
from pcc_ros.geometry.sampling import resample


class _Seeded(Dataset):
    def __init__(self, seed: int) -> None:
        self.seed = int(seed)
        self.epoch = 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def _rng(self, index: int) -> np.random.Generator:
        return np.random.default_rng((self.seed, self.epoch, int(index)))


class InstanceDataset(_Seeded):
    """Single observations of a split, resampled to ``n_points`` canonical points.

    Item: ``points`` float32 ``(n_points, 3)``, ``origin`` float32 ``(3,)`` (sensor in the
    canonical frame), ``num_points`` (observed count), ``index`` (cache row).
    """

    def __init__(self, cache: InstanceCache, split: str, n_points: int = 2048, seed: int = 0,
                 min_points: int = 1) -> None:
        super().__init__(seed)
        self.cache = cache
        self.n_points = n_points
        self.indices = cache.indices(split, min_points=min_points)
        if len(self.indices) == 0:
            raise DataError(f"{cache.root}: no instances in split {split!r} with >= {min_points} points")

    def __len__(self) -> int:
        return len(self.indices)

    def __getitem__(self, item: int) -> dict[str, torch.Tensor]:
        i = int(self.indices[item])
        pts = resample(np.asarray(self.cache.points(i)), self.n_points, self._rng(item))
        return {
            "points": torch.from_numpy(np.ascontiguousarray(pts, dtype=np.float32)),
            "origin": torch.from_numpy(self.cache.meta["origin"][i].astype(np.float32)),
            "num_points": torch.tensor(int(self.cache.meta["num_points"][i])),
            "index": torch.tensor(i),
        }


class MultiViewDataset(_Seeded):
    """PointPnCNet's multi-view training items: ``views`` observations of one group of
    ``group_size`` sequential observations of a track (a new draw every epoch).

    Item: ``views`` float32 ``(views, n_points, 3)``, ``indices`` ``(views,)``.
    """

    def __init__(self, cache: InstanceCache, split: str, views: int = 4, group_size: int = 20,
                 n_points: int = 2048, seed: int = 0, min_points: int = 1) -> None:
        super().__init__(seed)
        self.cache = cache
        self.views = views
        self.n_points = n_points
        self.groups = multiview_groups(cache, cache.indices(split, min_points=min_points), group_size, views)
        if not self.groups:
            raise DataError(f"{cache.root}: no track in split {split!r} has {views} observations")

    def __len__(self) -> int:
        return len(self.groups)

    def __getitem__(self, item: int) -> dict[str, torch.Tensor]:
        rng = self._rng(item)
        chosen = sample_views(self.groups[item], self.views, rng)
        clouds = np.stack([resample(np.asarray(self.cache.points(i)), self.n_points, rng) for i in chosen])
        return {"views": torch.from_numpy(clouds.astype(np.float32)), "indices": torch.from_numpy(chosen)}


class PoolDataset(_Seeded):
    """Whole-GT or Partial-GT pool entries resampled to ``n_points`` (TraPCC supervision).

    Item: ``points`` float32 ``(n_points, 3)`` and ``part`` (0 whole, 1 front, 2 back).
    """

    PARTS: ClassVar[dict[str, int]] = {"whole": 0, "front": 1, "back": 2}

    def __init__(self, entries: list[PoolEntry], n_points: int = 2048, seed: int = 0) -> None:
        super().__init__(seed)
        if not entries:
            raise DataError("empty pseudo-ground-truth pool")
        self.entries = entries
        self.n_points = n_points

    def __len__(self) -> int:
        return len(self.entries)

    def __getitem__(self, item: int) -> dict[str, torch.Tensor]:
        e = self.entries[item]
        pts = resample(e.points, self.n_points, self._rng(item))
        return {"points": torch.from_numpy(pts.astype(np.float32)), "part": torch.tensor(self.PARTS[e.part])}
