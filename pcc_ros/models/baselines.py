"""Non-learned baselines, registered as completers so they appear in every table.

* ``input``: the partial cloud itself. The floor every backend must beat; its coverage
  says how much of the car the sensor saw.
* ``densify``: PointPnCNet's "Densified Input" baseline (paper Table 2a, supplementary
  7.3.4): for each input point, the covariance of its 10 nearest neighbours defines an
  ellipsoid (principal axes = eigenvectors, semi-axes = ``axis_scale`` x sqrt(eigenvalue),
  i.e. one standard deviation by default) centred on the point, and points are sampled
  uniformly inside it. It adds density without adding unseen parts, which is what a
  completion method has to beat to show that it completes rather than densifies.
* ``mirror``: the input united with its reflection across the car's longitudinal x-z plane
  (canonical ``y -> -y``), the classic symmetry prior: a car seen from one side is
  completed on the other.

All are deterministic: random draws are seeded from each cloud's content and ``seed``.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from pcc_ros.errors import ConfigError
from pcc_ros.geometry.canonical import mirror_y
from pcc_ros.models.base import Completer, SceneContext, cloud_seed
from pcc_ros.models.registry import register


@register("input")
class InputCompleter(Completer):
    """Returns each partial cloud unchanged."""

    contains_input = True

    def __init__(self, device: str = "auto") -> None:
        super().__init__(device=device)

    def _complete(self, clouds: list[np.ndarray], contexts: list[SceneContext | None]) -> list[np.ndarray]:
        return [cloud.copy() for cloud in clouds]


@register("mirror")
class MirrorCompleter(Completer):
    """Input plus its mirror image across the canonical x-z plane (y -> -y)."""

    contains_input = True

    def __init__(self, device: str = "auto") -> None:
        super().__init__(device=device)

    def _complete(self, clouds: list[np.ndarray], contexts: list[SceneContext | None]) -> list[np.ndarray]:
        return [np.concatenate([cloud, mirror_y(cloud)]) for cloud in clouds]


def densify_cloud(
    cloud: np.ndarray,
    num_points: int,
    k: int = 10,
    axis_scale: float = 1.0,
    rng: np.random.Generator | None = None,
) -> np.ndarray:
    """``num_points`` samples drawn uniformly inside per-point neighbourhood ellipsoids.

    Vectorised over points: one KD-tree query, batched covariances and ``eigh``, and the
    samples are spread over the input points round-robin (every point gets
    ``num_points // N`` or one more; a random subset of points when ``N > num_points``).
    """
    rng = rng or np.random.default_rng(0)
    points = np.asarray(cloud, dtype=np.float64)
    n = len(points)
    k_eff = min(k, n)
    if k_eff >= 2:
        _, index = cKDTree(points).query(points, k=k_eff)  # (N, k) includes the point itself
        neighbours = points[index]  # (N, k, 3)
        centred = neighbours - neighbours.mean(axis=1, keepdims=True)
        cov = np.einsum("nki,nkj->nij", centred, centred) / k_eff
        eigval, eigvec = np.linalg.eigh(cov)  # columns of eigvec are the principal axes
        axes = eigvec * (axis_scale * np.sqrt(np.clip(eigval, 0.0, None)))[:, None, :]  # (N, 3, 3)
    else:
        axes = np.zeros((n, 3, 3))
    owner = np.arange(num_points) % n
    owner = rng.permutation(n)[owner] if n > num_points else owner
    # Uniform in the unit ball: Gaussian direction, radius u^(1/3).
    direction = rng.standard_normal((num_points, 3))
    direction /= np.maximum(np.linalg.norm(direction, axis=1, keepdims=True), 1e-12)
    ball = direction * np.cbrt(rng.random((num_points, 1)))
    samples = points[owner] + np.einsum("mij,mj->mi", axes[owner], ball)
    return samples.astype(np.float32)


@register("densify")
class DensifyCompleter(Completer):
    """PointPnCNet's densification baseline (10-NN covariance ellipsoids, uniform samples).

    Config: ``num_points`` (output size, default 2048, the usual completion output),
    ``k`` (neighbours, default 10 as in the paper), ``axis_scale`` (semi-axes in standard
    deviations, default 1), ``seed``.
    """

    def __init__(
        self,
        device: str = "auto",
        num_points: int = 2048,
        k: int = 10,
        axis_scale: float = 1.0,
        seed: int = 0,
        **config: Any,
    ) -> None:
        if config:
            raise ConfigError(f"densify: unknown option(s) {sorted(config)}")
        if num_points < 1 or k < 1 or axis_scale < 0:
            raise ConfigError(
                f"densify: need num_points >= 1, k >= 1, axis_scale >= 0 (got {num_points}, {k}, {axis_scale})"
            )
        super().__init__(device=device, num_points=num_points, k=k, axis_scale=axis_scale, seed=seed)
        self.num_points, self.k, self.axis_scale, self.seed = int(num_points), int(k), float(axis_scale), int(seed)

    def _complete(self, clouds: list[np.ndarray], contexts: list[SceneContext | None]) -> list[np.ndarray]:
        return [
            densify_cloud(
                cloud, self.num_points, self.k, self.axis_scale, np.random.default_rng(cloud_seed(cloud, self.seed))
            )
            for cloud in clouds
        ]
