"""Choosing AML's prior weight lambda (Eq. 4/5) with the ML baseline on validation data:
CD-L1 against SynthCars shapes and, with real crops, the distance of their held-out points."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from scipy.spatial import cKDTree

from pcc_ros.errors import ConfigError
from pcc_ros.geometry.voxels import box_aspect
from pcc_ros.metrics import instance_metrics
from pcc_ros.models.aml.completer import AML


@dataclass
class RealCrops:
    """Real crops for lambda validation: canonical clouds, canonical sensor origins, box sizes (m)."""

    clouds: list[np.ndarray]
    origins: np.ndarray
    sizes: np.ndarray

    def __len__(self) -> int:
        return len(self.clouds)


def real_crops(caches: Sequence[Any], split: str = "all", min_points: int = 10) -> RealCrops:
    """The crops of real instance caches, already open (``split``: one split or ``all``)."""
    clouds, origins, sizes = [], [], []
    for cache in caches:  # a handful of caches
        splits = ("train", "val", "test") if split == "all" else (split,)
        idx = np.concatenate([cache.indices(s, min_points=min_points) for s in splits]).astype(np.int64)
        clouds.extend(np.asarray(cache.points(int(i)), np.float32) for i in idx)
        origins.append(cache.meta["origin"][idx].astype(np.float64).reshape(-1, 3))
        sizes.append(cache.meta["box_size"][idx].astype(np.float64).reshape(-1, 3))
    return RealCrops(clouds, np.concatenate(origins) if origins else np.zeros((0, 3)),
                     np.concatenate(sizes) if sizes else np.zeros((0, 3)))


def _ml_completions(completer: AML, grids: torch.Tensor, clouds: Sequence[np.ndarray], aspects: np.ndarray,
                    steps: int, lam: float) -> list[np.ndarray]:
    """The ML baseline's (Eq. 4) completions of observation ``grids`` with prior weight ``lam``,
    fitted and decoded in chunks of 32 (what lambda selection scores, on either domain)."""
    outs: list[np.ndarray] = []
    for s in range(0, len(clouds), 32):
        z = completer.fit_latent(grids[s:s + 32, 0] > 0.5, grids[s:s + 32, 1] > 0.5, steps=steps, lam=lam)
        with torch.inference_mode():
            outs.extend(completer.decode_points(completer.model.decoder(z), clouds[s:s + 32], aspects[s:s + 32]))
    return outs


def holdout_fidelity(completer: AML, crops: RealCrops, lambdas: Sequence[float], steps: int, holdout: float,
                     seed: int, repeats: int = 3) -> dict[str, float]:
    """Per lambda: the ML baseline fitted to a seeded ``1 - holdout`` share of each real crop's
    points; score = mean distance (metres) of the held-out points to the completion.

    A real crop has no complete ground truth; its own unseen points are the honest check of
    how well a completion explains the car (too strong a prior misses them; the likelihood
    is what fits them). ``repeats`` seeded splits per crop."""
    kept, held, origins, aspects, lengths = [], [], [], [], []
    for r in range(repeats):
        for i, cloud in enumerate(crops.clouds):  # a few dozen crops: index bookkeeping only
            rng = np.random.default_rng([seed, r, i])
            mask = rng.random(len(cloud)) < holdout
            if mask.all() or not mask.any():
                mask[: max(1, len(cloud) // 3)] = True
                mask[-1] = False
            kept.append(cloud[~mask])
            held.append(cloud[mask])
            origins.append(crops.origins[i])
            aspects.append(box_aspect(crops.sizes[i]) if completer.config.get("frame") == "box" else np.ones(3))
            lengths.append(crops.sizes[i, 0])
    origins, aspects = np.asarray(origins), np.asarray(aspects)
    with torch.inference_mode():
        x = torch.cat([completer.observe_frame(kept[s:s + 32], origins[s:s + 32], aspects[s:s + 32])
                       for s in range(0, len(kept), 32)])
    table = {}
    for lam in lambdas:  # a handful of candidates
        outs = _ml_completions(completer, x, kept, aspects, steps, lam)
        dist = [float(cKDTree(o).query(h)[0].mean()) * length for o, h, length in zip(outs, held, lengths)]
        table[str(lam)] = float(np.mean(dist))
    return table


def select_lambda(completer: AML, instances: Sequence[Any], lambdas: Sequence[float], steps: int, seed: int,
                  real: RealCrops | None = None, real_weight: float = 0.5, holdout: float = 0.3
                  ) -> dict[str, Any]:
    """Run the ML baseline (Eq. 4) with each lambda on validation data; the lowest score wins.

    Synthetic: CD-L1 (canonical) against the true shapes of SynthCars ``val`` instances. Real
    (when ``real`` crops are given): :func:`holdout_fidelity` in metres. Score of a lambda:
    ``(1 - w) * cd / min(cd) + w * real / min(real)`` with ``w = real_weight`` (each domain
    relative to its best candidate, so neither's units dominate)."""
    if not instances:
        raise ConfigError("aml: lambda selection needs validation instances (--val-instances > 0)")
    if not lambdas:
        raise ConfigError("aml: --option lambdas is empty")
    table = {}
    clouds = [inst.partial for inst in instances]
    contexts = [getattr(inst, "context", None) for inst in instances]  # attached by pcc_ros.workflows.evaluate
    with torch.inference_mode():
        observed = [completer.observe(clouds[s:s + 32], contexts[s:s + 32]) for s in range(0, len(clouds), 32)]
    x = torch.cat([o[0] for o in observed])
    aspects = np.concatenate([o[1] for o in observed])
    for lam in lambdas:  # a handful of candidates
        outs = _ml_completions(completer, x, clouds, aspects, steps, lam)
        cd = [instance_metrics(o, inst.reference, None, length=inst.length, with_emd=False)["cd_l1"]
              for o, inst in zip(outs, instances)]
        table[str(lam)] = float(np.mean(cd))
    out: dict[str, Any] = {"table": table, "metric": "val cd_l1 (canonical) of the ML baseline",
                           "instances": len(instances), "steps": steps, "seed": seed}
    score = {k: v / min(table.values()) for k, v in table.items()}
    if real is not None and len(real):
        real_table = holdout_fidelity(completer, real, lambdas, steps, holdout, seed)
        best = min(real_table.values())
        score = {k: (1 - real_weight) * score[k] + real_weight * real_table[k] / best for k in table}
        out.update({"real_table": real_table, "real_crops": len(real), "real_weight": real_weight,
                    "real_metric": f"held-out real points -> ML completion, metres ({holdout:.0%} of each "
                                   "crop's points held out, 3 seeded splits)", "score": score})
    out["chosen"] = float(min(score, key=score.get))
    return out
