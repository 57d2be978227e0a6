"""``pcc train aml --stage prior|encoder``: the training recipe (driven by :mod:`pcc_ros.workflows.train`)."""

from __future__ import annotations

import contextlib
import hashlib
import logging
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from pcc_ros.errors import CheckpointError, ConfigError
from pcc_ros.files import atomic_write
from pcc_ros.geometry.voxels import box_aspect, observation_grids, to_box_frame
from pcc_ros.metrics.balance import track_partners
from pcc_ros.models.aml.completer import AML
from pcc_ros.models.aml.lambda_selection import real_crops, select_lambda
from pcc_ros.models.aml.likelihood import observed_nll
from pcc_ros.models.aml.network import DEFAULT_ASPECT, GRIDS, PRESETS, grid_of
from pcc_ros.models.aml.prior import (
    PriorBatch,
    ReferenceSet,
    augment_grids,
    hash_split,
    synthcars_reference_shapes,
    vae_loss,
    validate_prior,
    whiten_latent,
)
from pcc_ros.models.checkpoint import load_checkpoint
from pcc_ros.models.recipe import TrainingKit, TrainingRecipe

log = logging.getLogger(__name__)


@dataclass
class ObservationBatch:
    occupied: torch.Tensor  # (B, H, L, W) bool
    free: torch.Tensor
    #: with ``pairs`` = P > 0, instance ``i < P`` and instance ``P + i`` are two observations of one car
    pairs: int = 0

    def to(self, device: torch.device) -> ObservationBatch:
        return ObservationBatch(self.occupied.to(device), self.free.to(device), self.pairs)

    def grids(self) -> torch.Tensor:
        return torch.stack([self.occupied, self.free], 1).float().contiguous(memory_format=torch.channels_last_3d)


@dataclass
class Observations:
    """Partial observations for the encoder: canonical clouds, their sensor origins (canonical)
    and box aspects ``(1, w / l, h / l)``."""

    clouds: list[np.ndarray]
    origins: np.ndarray
    sources: dict[str, int]
    aspects: np.ndarray | None = None
    #: index of the same car's observation in the nearest other frame (itself when it has none)
    partner: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.clouds)


class AMLRecipe(TrainingRecipe):
    """``pcc train aml --stage prior|encoder`` (driven by :mod:`pcc_ros.workflows.train`).

    * ``prior``: ``--data`` is a SynthCars root; the VAE learns the voxelised complete shapes
      of its train sequences (90 % / 10 % hash split into train / validation shapes).
      Validation: the VAE loss and the reconstruction IoU of the held-out shapes.
    * ``encoder``: ``--data`` is an instance cache of partial observations, plus ``real``
      (comma-separated caches of real KITTI / nuScenes crops); ``prior`` names the prior
      checkpoint. The decoder is loaded and frozen; lambda is chosen first by the ML
      baseline on validation instances among ``lambdas``; validation: the evaluation
      metrics of the encoder (``val_cd_l1``) on the validation split.
    """

    name = "aml"
    default_lr = 1e-3

    def __init__(self, size: str = "default", stage: str = "prior", prior: str | None = None,
                 lambdas: str | Sequence[float] = (0.1, 1.0, 10.0), lam: float | None = None,
                 real: str | None = None, real_repeat: int = 4, lambda_instances: int = 96,
                 lambda_steps: int = 40, beta: float = 1.0, augment: bool = True, max_shapes: int = 600,
                 reference_cache: str | None = None, real_split: str = "train", box_jitter: float = 0.06,
                 lambda_real_weight: float = 0.5, lambda_holdout: float = 0.3,
                 encoder_init: str | None = None, consistency: float = 0.0) -> None:
        if stage not in ("prior", "encoder"):
            raise ConfigError(f"aml: --stage must be prior or encoder, got {stage!r}")
        if stage == "encoder" and not prior:
            raise ConfigError("aml --stage encoder needs the prior: --option prior=RUN/aml.safetensors")
        self.size, self.stage, self.prior = size, stage, prior
        #: encoder stage: start the observation encoder from this checkpoint's ``encoder.*`` weights
        #: (e.g. the shipped AML after a prior fine-tune: a warm start in a nearby latent space)
        self.encoder_init = encoder_init
        if isinstance(lambdas, str):
            lambdas = [float(v) for v in lambdas.split(",") if v.strip()]
        self.lambdas = [float(v) for v in lambdas]
        self.fixed_lam = lam
        self.real = [p for p in (real or "").split(",") if p.strip()]
        self.real_repeat = int(real_repeat)
        self.lambda_instances = int(lambda_instances)
        self.lambda_steps = int(lambda_steps)
        self.beta = float(beta)
        self.augment = bool(augment)
        self.max_shapes = int(max_shapes)
        self.reference_cache = reference_cache
        if real_split not in ("train", "val", "test", "all"):
            raise ConfigError(f"aml: real_split must be train, val, test or all, got {real_split!r}")
        self.real_split = real_split
        self.box_jitter = float(box_jitter)
        if not 0 <= self.box_jitter < 0.5:
            raise ConfigError(f"aml: box_jitter must be in [0, 0.5), got {box_jitter}")
        self.lambda_real_weight = float(lambda_real_weight)
        self.lambda_holdout = float(lambda_holdout)
        if not 0 < self.lambda_holdout < 1:
            raise ConfigError(f"aml: lambda_holdout must be in (0, 1), got {lambda_holdout}")
        #: encoder stage: weight of ``||z_a - z_b||^2 / 2`` between two observations of one car in
        #: neighbouring frames (each with its own box jitter), on the scale of lambda's ``||z||^2 / 2``
        self.consistency = float(consistency)
        if self.consistency < 0:
            raise ConfigError(f"aml: consistency must be >= 0, got {consistency}")
        self.select_metric = "val_loss" if stage == "prior" else "val_cd_l1"
        self.lambda_sweep: dict[str, Any] = {}
        self.whitening: dict[str, Any] = {}
        self.completer: AML | None = None

    def describe(self) -> dict[str, Any]:
        return {"size": self.size, "stage": self.stage, "prior": self.prior, "lambdas": self.lambdas,
                "lam": self.fixed_lam, "real": self.real, "real_repeat": self.real_repeat, "beta": self.beta,
                "augment": self.augment, "lambda_instances": self.lambda_instances,
                "lambda_steps": self.lambda_steps, "max_shapes": self.max_shapes, "real_split": self.real_split,
                "box_jitter": self.box_jitter, "lambda_real_weight": self.lambda_real_weight,
                "lambda_holdout": self.lambda_holdout, "encoder_init": self.encoder_init,
                "consistency": self.consistency}

    # ---- model

    def build_completer(self, device: str) -> AML:
        completer = AML(device=device, size=self.size)
        if self.stage == "encoder":
            state, config = load_checkpoint(self.prior)
            if config["backend"] != "aml":
                raise CheckpointError(f"{self.prior}: not an AML checkpoint (backend {config['backend']!r})")
            if config.get("hyper_parameters") != completer.config:
                raise CheckpointError(f"{self.prior}: prior was trained with another model config")
            prior_state = {k: v for k, v in state.items() if not k.startswith("encoder.")}
            missing, unexpected = completer.model.load_state_dict(prior_state, strict=False)
            if unexpected or any(not k.startswith("encoder.") for k in missing):
                raise CheckpointError(f"{self.prior}: prior weights do not fit ({missing[:3]} {unexpected[:3]})")
            if self.encoder_init:
                state, _ = load_checkpoint(self.encoder_init)
                own = completer.model.state_dict()
                encoder = {k: v for k, v in state.items() if k.startswith("encoder.")}
                if not encoder or any(k not in own or own[k].shape != v.shape for k, v in encoder.items()):
                    raise CheckpointError(f"{self.encoder_init}: no encoder weights of this model (encoder_init)")
                completer.model.load_state_dict(encoder, strict=False)
            completer.model.freeze_decoder()
        self.completer = completer
        return completer

    # ---- data

    def open_data(self, path: Path) -> Any:
        """Prior stage: the voxelised reference shapes of a SynthCars root; encoder stage: a cache."""
        if self.stage == "prior":
            return self._reference_shapes(Path(path))
        return super().open_data(path)

    def _reference_shapes(self, root: Path) -> ReferenceSet:
        """The voxelised reference set, read from / written to ``reference_cache`` when given."""
        truncation = float(PRESETS[self.size]["truncation"])
        frame = str(PRESETS[self.size]["frame"])
        cache = Path(self.reference_cache) if self.reference_cache else None
        # the root by its meta.json's content (seed, parameters, splits), not its path: a cache made
        # here is reused where the same dataset lies elsewhere (another machine, a copied folder)
        try:
            content = hashlib.sha256((root / "meta.json").read_bytes()).hexdigest()[:16]
        except OSError:
            content = str(root.resolve())  # not a SynthCars root: synthcars_reference_shapes says so below
        stamp = f"{content}|{self.max_shapes}|{truncation}|{frame}|{GRIDS[frame]}|sdf-voxel-steps|f16"
        if cache is not None and cache.is_file():
            with np.load(cache, allow_pickle=False) as z:
                if str(z["stamp"]) == stamp:
                    log.info("aml: reference grids from %s", cache)
                    return ReferenceSet(z["occupancy"], z["sdf"].astype(np.float32), [str(k) for k in z["keys"]])
            log.info("aml: %s was made from other shapes or settings; recomputing", cache)
        ref = synthcars_reference_shapes(root, truncation, self.max_shapes, frame=frame)
        if cache is not None:
            cache.parent.mkdir(parents=True, exist_ok=True)
            with atomic_write(cache, "wb") as stream:
                # the truncated SDF (|d| <= a few voxels) in float16: half the file, 1e-3 voxel steps
                np.savez_compressed(stream, occupancy=ref.occupancy, sdf=ref.sdf.astype(np.float16),
                                    keys=np.array(ref.keys), stamp=stamp)
        return ref

    def training_data(self, source: Any, split: str, min_points: int = 10) -> Any:
        if self.stage == "prior":
            val = hash_split(source.keys, 0.1)
            return source.subset(np.flatnonzero(~val))

        clouds, origins, aspects, partners, sources = [], [], [], [], {}
        open_cache = TrainingKit.require(self.kit, self.name).open_cache if self.real else None
        caches = [(source, 1, split)] + [(open_cache(p), self.real_repeat, self.real_split) for p in self.real]
        for cache, repeat, which in caches:  # a handful of caches
            idx = cache.indices(which, min_points=min_points) if which != "all" else np.concatenate(
                [cache.indices(s, min_points=min_points) for s in ("train", "val", "test")])
            pts = [np.asarray(cache.points(int(i)), np.float32) for i in idx]
            sources[str(cache.root)] = len(idx)
            meta = cache.meta
            partner = track_partners(meta["sequence"][idx], meta["track"][idx], meta["frame"][idx])
            for _ in range(repeat):  # real crops are few: repeated so a batch sees them
                partners.append(partner + len(clouds))
                clouds.extend(pts)
                origins.append(cache.meta["origin"][idx].astype(np.float64))
                aspects.append(box_aspect(cache.meta["box_size"][idx]))
        if not clouds:
            raise ConfigError(f"aml: no training observations in split {split!r}")
        return Observations(clouds, np.concatenate(origins), sources, np.concatenate(aspects),
                            np.concatenate(partners))

    def batches(self, data: Any, batch_size: int, cfg: dict[str, Any], rng: np.random.Generator) -> Iterator[Any]:
        n = len(data)
        if n == 0:
            raise ConfigError("aml: empty training set")
        while True:
            order = rng.permutation(n) if n >= batch_size else rng.integers(n, size=batch_size)
            for start in range(0, len(order) - batch_size + 1, batch_size):
                pick = order[start:start + batch_size]
                if self.stage == "prior":
                    occ = torch.from_numpy(data.occupancy[pick].astype(np.float32))
                    sdf = torch.from_numpy(data.sdf[pick])
                    if self.augment:
                        occ, sdf = augment_grids(occ, sdf, rng, spec=grid_of(cfg),
                                                 axis_scale=self.box_jitter if cfg.get("frame") == "box" else 0.0)
                    yield PriorBatch(occ.contiguous(), sdf.contiguous())
                elif self.consistency > 0 and data.partner is not None:  # each car twice: two frames
                    batch = self.observation_batch(data, np.concatenate([pick, data.partner[pick]]), cfg, rng)
                    batch.pairs = len(pick)
                    yield batch
                else:
                    yield self.observation_batch(data, pick, cfg, rng)

    def observation_batch(self, data: Observations, pick: np.ndarray, cfg: dict[str, Any],
                          rng: np.random.Generator) -> ObservationBatch:
        """Observation grids of ``data[pick]`` in the grid's frame. In the box frame each box is
        jittered (``box_jitter``: per-axis size factor in ``[1 - j/2, 1 + j]``, centre shift
        ``N(0, j/3)`` box units) when ``augment`` is on: labelled and detected boxes do not
        fit their cars exactly."""
        clouds = [data.clouds[i] for i in pick]
        origins = data.origins[pick]
        if cfg.get("frame", "box") == "box":
            aspects = data.aspects[pick] if data.aspects is not None else np.tile(DEFAULT_ASPECT, (len(pick), 1))
            shift = np.zeros((len(pick), 3))
            if self.augment and self.box_jitter > 0:
                aspects = aspects * rng.uniform(1 - self.box_jitter / 2, 1 + self.box_jitter, (len(pick), 3))
                shift = rng.normal(0.0, self.box_jitter / 3, (len(pick), 3)) * aspects
            clouds = [to_box_frame(c - t, a) for c, t, a in zip(clouds, shift, aspects)]
            origins = to_box_frame(origins - shift, aspects)
        occupied, free = observation_grids(clouds, origins, grid_of(cfg), stop=float(cfg["stop"]),
                                           max_rays=int(cfg["max_rays"]))
        return ObservationBatch(torch.from_numpy(occupied), torch.from_numpy(free))

    # ---- losses

    def loss(self, net: nn.Module, batch: Any) -> tuple[torch.Tensor, dict[str, float]]:
        cfg = PRESETS[self.size]
        if self.stage == "prior":
            return vae_loss(net, batch, float(cfg["log_var"]), float(cfg["truncation"]), self.beta)
        lam = self.completer.lam if self.completer is not None else 1.0
        z, decoded = net(batch.grids())
        nll = observed_nll(decoded, batch.occupied, batch.free, float(cfg["log_var"]))
        prior = 0.5 * (z**2).sum(1)
        observed = (batch.occupied | batch.free).flatten(1).sum(1).clamp(min=1).float()
        loss = (nll + lam * prior).mean()
        stats: dict[str, float] = {}
        if batch.pairs:  # one car seen in two frames: one code (the shape did not change)
            p = batch.pairs
            gap = 0.5 * ((z[:p] - z[p:2 * p]) ** 2).sum(1)
            loss = loss + self.consistency * gap.mean()
            stats["z_gap"] = float(gap.detach().mean())
        loss = loss / observed.mean()
        return loss, {"loss": float(loss.detach()), "nll_per_voxel": float((nll / observed).mean().detach()),
                      "z_norm": float(z.detach().norm(dim=1).mean()), **stats}

    # ---- validation and lambda selection

    def validation_data(self, source: Any, split: str, count: int, seed: int) -> tuple[Any, str]:
        if self.stage == "prior":
            val = hash_split(source.keys, 0.1)
            return source.subset(np.flatnonzero(val)), "held-out reference shapes"
        return super().validation_data(source, split, count, seed)

    def validate(self, completer: AML, val_data: Any, seed: int) -> dict[str, float]:
        if self.stage == "prior":
            return validate_prior(completer, val_data, self.beta)
        return super().validate(completer, val_data, seed)

    def prepare(self, completer: AML, data: Any, val_data: Any, seed: int) -> None:
        """Encoder stage: choose lambda with the ML baseline on validation instances."""
        if self.stage != "encoder":
            return
        if self.fixed_lam is not None:
            completer.lam = float(self.fixed_lam)
            self.lambda_sweep = {"chosen": completer.lam, "how": "given (--option lam)"}
            return
        real = None
        if self.real and self.lambda_real_weight > 0:
            open_cache = TrainingKit.require(self.kit, self.name).open_cache
            real = real_crops([open_cache(p) for p in self.real], "all")
        self.lambda_sweep = select_lambda(completer, val_data[: self.lambda_instances], self.lambdas,
                                          self.lambda_steps, seed, real=real, real_weight=self.lambda_real_weight,
                                          holdout=self.lambda_holdout)
        completer.lam = float(self.lambda_sweep["chosen"])
        log.info("aml: lambda %.3g chosen on %d validation instances: %s", completer.lam,
                 self.lambda_sweep["instances"], self.lambda_sweep["table"])

    @contextlib.contextmanager
    def saving(self, completer: AML, data: Any) -> Iterator[None]:
        """Prior stage: the saved weights have a whitened latent space (:func:`whiten_latent`); training
        continues with its own weights."""
        if self.stage != "prior":
            yield
            return
        current = {k: v.clone() for k, v in completer.model.state_dict().items()}
        self.whitening = whiten_latent(completer.model, data, float(completer.config["truncation"]))
        log.info("aml: latent whitened on %d reference shapes: %s", len(data), self.whitening)
        try:
            yield
        finally:
            completer.model.load_state_dict(current)

    def summary(self) -> dict[str, Any]:
        """Extra facts for the checkpoint (the lambda sweep, the latent whitening)."""
        out: dict[str, Any] = {}
        if self.lambda_sweep:
            out["lambda_selection"] = self.lambda_sweep
        if self.whitening:
            out["latent_whitening"] = self.whitening
        return out


@AML.trains_with
def training_recipe(size: str = "default", **options: Any) -> AMLRecipe:
    """The training recipe ``pcc train aml`` uses (see :mod:`pcc_ros.workflows.train`)."""
    return AMLRecipe(size=size, **options)
