"""Choosing AML's inference settings on validation data: the prior weight lambda (Eq. 4/5) with
the ML baseline, and the refinement of the encoder's codes by Eq. 4 (steps, learning rate), both
by CD-L1 against SynthCars shapes and, with real crops, the distance of their held-out points."""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
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


#: Codes of one chunk of observation grids ``(b, 2, H, L, W) -> (b, Q)``: one candidate setting of a selection.
Codes = Callable[[torch.Tensor], torch.Tensor]


def ml_codes(completer: AML, steps: int, lam: float) -> Codes:
    """The ML baseline's (Eq. 4, from ``z = 0``) codes with prior weight ``lam``."""
    return lambda grids: completer.fit_latent(grids[:, 0] > 0.5, grids[:, 1] > 0.5, steps=steps, lam=lam)


def refined_codes(completer: AML, steps: int, lr: float) -> Codes:
    """The amortized encoder's codes refined by ``steps`` Adam steps of Eq. 4 at ``lr``
    (:meth:`AML.latent_codes` with that refinement; the completer's own setting is restored)."""
    def codes(grids: torch.Tensor) -> torch.Tensor:
        kept = completer.refine_steps, completer.refine_lr
        completer.set_refinement(steps, lr)
        try:
            with torch.inference_mode():
                return completer.latent_codes(grids)
        finally:
            completer.set_refinement(*kept)
    return codes


def _completions(completer: AML, grids: torch.Tensor, clouds: Sequence[np.ndarray], aspects: np.ndarray,
                 codes: Codes) -> list[np.ndarray]:
    """Completions of observation ``grids`` decoded from ``codes``, in chunks of 32 (what a
    selection scores, on either domain)."""
    outs: list[np.ndarray] = []
    for s in range(0, len(clouds), 32):
        z = codes(grids[s:s + 32])
        with torch.inference_mode():
            outs.extend(completer.decode_points(completer.model.decoder(z), clouds[s:s + 32], aspects[s:s + 32]))
    return outs


def holdout_fidelity(completer: AML, crops: RealCrops, candidates: Mapping[str, Codes], holdout: float,
                     seed: int, repeats: int = 3) -> dict[str, float]:
    """Per candidate (e.g. :func:`ml_codes` of each lambda): the codes fitted to a seeded
    ``1 - holdout`` share of each real crop's points; score = mean distance (metres) of the
    held-out points to the completion.

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
    for name, codes in candidates.items():  # a handful of candidates
        outs = _completions(completer, x, kept, aspects, codes)
        dist = [float(cKDTree(o).query(h)[0].mean()) * length for o, h, length in zip(outs, held, lengths)]
        table[name] = float(np.mean(dist))
    return table


def _select(completer: AML, instances: Sequence[Any], candidates: Mapping[str, Codes], seed: int,
            real: RealCrops | None, real_weight: float, holdout: float) -> dict[str, Any]:
    """Score each candidate on validation data; the lowest score wins.

    Synthetic: CD-L1 (canonical) against the true shapes of SynthCars ``val`` instances. Real
    (when ``real`` crops are given): :func:`holdout_fidelity` in metres. Score of a candidate:
    ``(1 - w) * cd / min(cd) + w * real / min(real)`` with ``w = real_weight`` (each domain
    relative to its best candidate, so neither's units dominate)."""
    if not instances:
        raise ConfigError("aml: selection needs validation instances (--val-instances > 0)")
    if not candidates:
        raise ConfigError("aml: nothing to select from (an empty list of candidates)")
    table = {}
    clouds = [inst.partial for inst in instances]
    contexts = [getattr(inst, "context", None) for inst in instances]  # attached by pcc_ros.workflows.evaluate
    with torch.inference_mode():
        observed = [completer.observe(clouds[s:s + 32], contexts[s:s + 32]) for s in range(0, len(clouds), 32)]
    x = torch.cat([o[0] for o in observed])
    aspects = np.concatenate([o[1] for o in observed])
    for name, codes in candidates.items():  # a handful of candidates
        outs = _completions(completer, x, clouds, aspects, codes)
        cd = [instance_metrics(o, inst.reference, None, length=inst.length, with_emd=False)["cd_l1"]
              for o, inst in zip(outs, instances)]
        table[name] = float(np.mean(cd))
    out: dict[str, Any] = {"table": table, "instances": len(instances), "seed": seed}
    score = {k: v / min(table.values()) for k, v in table.items()}
    if real is not None and len(real):
        real_table = holdout_fidelity(completer, real, candidates, holdout, seed)
        best = min(real_table.values())
        score = {k: (1 - real_weight) * score[k] + real_weight * real_table[k] / best for k in table}
        out.update({"real_table": real_table, "real_crops": len(real), "real_weight": real_weight,
                    "real_metric": f"held-out real points -> completion, metres ({holdout:.0%} of each "
                                   "crop's points held out, 3 seeded splits)", "score": score})
    out["chosen"] = min(score, key=score.get)
    return out


def select_lambda(completer: AML, instances: Sequence[Any], lambdas: Sequence[float], steps: int, seed: int,
                  real: RealCrops | None = None, real_weight: float = 0.5, holdout: float = 0.3
                  ) -> dict[str, Any]:
    """Run the ML baseline (Eq. 4) with each lambda on validation data (:func:`_select`'s score)."""
    if not lambdas:
        raise ConfigError("aml: --option lambdas is empty")
    out = _select(completer, instances, {str(lam): ml_codes(completer, steps, lam) for lam in lambdas}, seed, real,
                  real_weight, holdout)
    out.update({"metric": "val cd_l1 (canonical) of the ML baseline", "steps": steps, "chosen": float(out["chosen"])})
    return out


def select_refinement(completer: AML, instances: Sequence[Any], steps: Sequence[int], lrs: Sequence[float],
                      seed: int, real: RealCrops | None = None, real_weight: float = 0.5, holdout: float = 0.3
                      ) -> dict[str, Any]:
    """Choose ``refine_steps`` / ``refine_lr`` (the encoder's codes refined by Eq. 4 at the
    completer's lambda) from a grid on validation data, by :func:`_select`'s score; candidates
    are named ``"STEPS@LR"`` (step count 0 once: no refinement, whatever the rate)."""
    grid = sorted({(int(n), float(lr) if n else 0.0) for n in steps for lr in lrs})
    out = _select(completer, instances, {f"{n}@{lr:g}": refined_codes(completer, n, lr or completer.refine_lr)
                                         for n, lr in grid}, seed, real, real_weight, holdout)
    n, lr = out["chosen"].split("@")
    out.update({"metric": "val cd_l1 (canonical) of the encoder refined by Eq. 4", "lam": completer.lam,
                "refine_steps": int(n), "refine_lr": float(lr) or completer.refine_lr})
    return out
