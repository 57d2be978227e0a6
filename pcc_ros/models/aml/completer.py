"""The AML completers: ``aml`` (the amortized encoder, optionally refined by a few steps of the
per-instance objective) and ``aml_ml`` (the ML baseline, Eq. 4: ``z`` optimised per instance from
``z = 0``), sharing the prior's weights."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from pcc_ros.errors import CheckpointError, ConfigError
from pcc_ros.geometry.canonical import to_canonical
from pcc_ros.geometry.voxels import (
    GridSpec,
    box_aspect,
    estimate_origin,
    from_box_frame,
    observation_grids,
    to_box_frame,
)
from pcc_ros.models.aml.likelihood import observed_nll
from pcc_ros.models.aml.network import DEFAULT_ASPECT, PRESETS, AMLNet, grid_of
from pcc_ros.models.aml.surface import surface_samples
from pcc_ros.models.base import ASPECT_SCALE_RANGE, SceneContext, TorchCompleter, cloud_seed
from pcc_ros.models.registry import register

log = logging.getLogger(__name__)


def box_aspects(contexts: Sequence[SceneContext | None]) -> np.ndarray:
    """``(B, 3)`` box aspect ``(1, w / l, h / l)`` of each instance: its context's box, else
    :data:`DEFAULT_ASPECT`; ``w / l`` and ``h / l`` clipped to ``ASPECT_SCALE_RANGE`` times the
    default (as the shared :func:`~pcc_ros.models.base.aspect_scales`): a detector box twice
    as wide or tall as a car is not a car body the prior can fill."""
    default = np.asarray(DEFAULT_ASPECT, np.float64)
    out = np.tile(default, (len(contexts), 1))
    for i, ctx in enumerate(contexts):  # per instance: one 3-vector
        if ctx is not None:
            out[i] = box_aspect(ctx.box.size[0])
    low, high = ASPECT_SCALE_RANGE
    out[:, 1:] = np.clip(out[:, 1:], default[1:] * low, default[1:] * high)
    return out


def canonical_origins(clouds: Sequence[np.ndarray], contexts: Sequence[SceneContext | None]) -> np.ndarray:
    """Sensor origin of each cloud in its canonical frame: exact from a context's box, else estimated."""
    out = np.empty((len(clouds), 3))
    for i, (cloud, ctx) in enumerate(zip(clouds, contexts)):  # per instance: one 3-vector
        if ctx is None:
            out[i] = estimate_origin(cloud)
        else:
            box = ctx.box
            out[i] = to_canonical(ctx.sensor_origin[None], box.center[0], float(box.yaw[0]), float(box.size[0, 0]))[0]
    return out


@register("aml")
class AML(TorchCompleter):
    """AML completer: canonical partial clouds (+ sensor origin via the scene context) in,
    ``output_points`` canonical points on the decoded car surface out.

    Without a :class:`SceneContext` the sensor origin (for free space) is estimated from
    the side the points face (:func:`~pcc_ros.geometry.voxels.estimate_origin`).

    ``refine_steps`` / ``refine_lr`` (run-time; default: the checkpoint's ``training.refine_steps``
    / ``training.refine_lr``, else 0 / :attr:`ml_lr`): amortised-then-refined inference, the
    encoder's code as the start of that many Adam steps of Eq. 4 (:meth:`fit_latent`), for the
    scans the encoder maps to too common a car (its amortization gap). 0: the encoder's code as is.
    """

    uses_context = True
    #: Per-instance optimisation of z instead of the amortized encoder (the ML baseline).
    inference = "aml"

    #: The named sizes of the network.
    presets = PRESETS

    def __init__(self, device: str = "auto", refine_steps: int | None = None, refine_lr: float | None = None,
                 **options: Any) -> None:
        #: lambda of Eq. 4/5 (set from the checkpoint; training selects it on validation).
        self.lam = 1.0
        self.ml_steps = 40
        self.ml_lr = 0.15
        self.refine_steps, self.refine_lr = 0, self.ml_lr
        self.set_refinement(refine_steps, refine_lr)
        # options: size (a preset), hyper-parameters overriding it, and run-time options (batch_size, ...)
        super().__init__(device=device, **options)

    def build_model(self) -> AMLNet:
        if len(self.config["channels"]) != 3:
            raise ConfigError(f"aml: channels must list three stage widths, got {self.config['channels']}")
        # channels-last 3D: oneDNN's preferred convolution layout on CPU
        return AMLNet(int(self.config["latent"]), self.config["channels"]).to(memory_format=torch.channels_last_3d)

    # ---- checkpoints: lambda is "training.lam" in the JSON config (chosen after the
    # model is built, so it is not a constructor hyper-parameter)

    def save(self, path: str | Path, *, training: dict[str, Any] | None = None,
             metrics: dict[str, Any] | None = None, extra: dict[str, Any] | None = None) -> Path:
        return super().save(path, training={**(training or {}), "lam": self.lam}, metrics=metrics, extra=extra)

    def set_refinement(self, steps: int | None = None, lr: float | None = None) -> None:
        """Set the encoder-then-Eq. 4 refinement (``None`` keeps a setting); refused unless
        ``steps`` is an integer >= 0 and ``lr`` a positive finite number."""
        if steps is not None:
            if isinstance(steps, bool) or not isinstance(steps, (int, np.integer)) or steps < 0:
                raise ConfigError(f"aml: refine_steps must be an integer >= 0, got {steps!r}")
            self.refine_steps = int(steps)
        if lr is not None:
            if isinstance(lr, bool) or not isinstance(lr, (int, float)) or not 0 < lr < float("inf"):
                raise ConfigError(f"aml: refine_lr must be a positive number, got {lr!r}")
            self.refine_lr = float(lr)

    @classmethod
    def from_checkpoint(cls, path: str | Path, device: str = "auto", **overrides: Any) -> AML:
        completer = super().from_checkpoint(path, device=device, **overrides)
        training = (completer.checkpoint_config or {}).get("training", {})
        lam = training.get("lam")
        if lam is not None:
            if not (isinstance(lam, (int, float)) and lam >= 0):
                raise CheckpointError(f"{path}: invalid lambda {lam!r}")
            completer.lam = float(lam)
        stored = {k: training.get(f"refine_{k}") for k in ("steps", "lr") if overrides.get(f"refine_{k}") is None}
        try:  # the run-time options given win over the checkpoint's
            completer.set_refinement(stored.get("steps"), stored.get("lr"))
        except ConfigError as exc:
            raise CheckpointError(f"{path}: invalid training.refine_* entry: {exc}") from exc
        return completer

    # ---- inference

    def points_per_car(self) -> int:
        """Points sampled on each mesh: ``output_points``, times the point multiplier a 2 x 2
        folding grid gets at the run-time ``decode_density`` d, ((d + 1) / 2)^2 (2.25 at the node's
        default 2): the same denser output as the folding backends, drawn on the same mesh."""
        d = int(getattr(self, "decode_density", 1))
        return round(int(self.config["output_points"]) * ((d + 1) / 2) ** 2)

    @property
    def grid(self) -> GridSpec:
        """The voxel grid of this model's frame (``frame`` hyper-parameter)."""
        return grid_of(self.config)

    def aspects(self, contexts: Sequence[SceneContext | None]) -> np.ndarray:
        """``(B, 3)`` scale from the grid's frame to the canonical frame (ones for ``frame: canonical``)."""
        if self.config.get("frame", "box") == "canonical":
            return np.ones((len(contexts), 3))
        return box_aspects(contexts)

    def observe(self, clouds: Sequence[np.ndarray], contexts: Sequence[SceneContext | None]
                ) -> tuple[torch.Tensor, np.ndarray]:
        """``(B, 2, H, L, W)`` float observation grids (occupied, free) on the model's device, and
        the ``(B, 3)`` aspects that map the grid's frame back to the canonical one."""
        aspects = self.aspects(contexts)
        return self.observe_frame(clouds, canonical_origins(clouds, contexts), aspects), aspects

    def observe_frame(self, clouds: Sequence[np.ndarray], origins: np.ndarray, aspects: np.ndarray) -> torch.Tensor:
        """Observation grids of canonical clouds with canonical sensor ``origins`` and box ``aspects``."""
        occupied, free = observation_grids([to_box_frame(c, a) for c, a in zip(clouds, aspects)],
                                           to_box_frame(origins, aspects), self.grid,
                                           stop=float(self.config["stop"]), max_rays=int(self.config["max_rays"]))
        # built channels-last (B, H, L, W, 2) and viewed as (B, 2, H, L, W): oneDNN's layout, no copy
        grids = np.empty((*occupied.shape, 2), np.float32)
        grids[..., 0], grids[..., 1] = occupied, free
        return torch.from_numpy(grids).permute(0, 4, 1, 2, 3).to(self.device)

    def decode_points(self, decoded: torch.Tensor, clouds: Sequence[np.ndarray], aspects: np.ndarray
                      ) -> list[np.ndarray]:
        """Decoded grids -> marching cubes on the SDF -> surface samples (one canonical cloud each)."""
        sdf = decoded[:, 1].float().cpu().numpy()
        points = surface_samples(sdf, self.grid, aspects, self.points_per_car(),
                                 [cloud_seed(c) for c in clouds])
        missing = [i for i, p in enumerate(points) if len(p) == 0]
        if missing:  # no zero crossing: fall back to the decoded occupancy, then the input
            log.warning("aml: %d decoded shape(s) without a surface; using occupied voxels", len(missing))
            occ = decoded[:, 0].float().cpu().numpy() > 0
            centres = self.grid.centers()
            for i in missing:
                points[i] = (from_box_frame(centres[occ[i]], aspects[i]).astype(np.float32) if occ[i].any()
                             else np.asarray(clouds[i], np.float32))
        return points

    def latent_codes(self, x: torch.Tensor) -> torch.Tensor:
        """``(B, Q)`` codes of observation grids ``x``: Eq. 4 from ``z = 0`` (``aml_ml``), or the
        amortized encoder's code, refined by ``refine_steps`` steps of Eq. 4 when set."""
        occupied, free = x[:, 0] > 0.5, x[:, 1] > 0.5
        if self.inference == "ml":
            return self.fit_latent(occupied, free)
        z = self.model.encoder(x)
        if self.refine_steps:
            z = self.fit_latent(occupied, free, steps=self.refine_steps, init=z, lr=self.refine_lr)
        return z

    def forward_batch(self, clouds: list[np.ndarray], contexts: list[SceneContext | None]) -> list[np.ndarray]:
        x, aspects = self.observe(clouds, contexts)
        z = self.latent_codes(x)
        decoded = self.model.decoder(z.to(next(self.model.decoder.parameters()).dtype))
        return self.decode_points(decoded, clouds, aspects)

    def fit_latent(self, occupied: torch.Tensor, free: torch.Tensor, steps: int | None = None,
                   lam: float | None = None, init: torch.Tensor | None = None, lr: float | None = None
                   ) -> torch.Tensor:
        """Eq. 4: ``argmin_z`` of the observed-voxel NLL + ``lam ||z||^2 / 2`` by ``steps`` Adam
        steps of learning rate ``lr`` (default :attr:`ml_lr`), from ``init`` (``(B, Q)``, e.g. the
        encoder's codes) or ``z = 0``.

        Batched over instances: the objective is a sum of independent per-instance terms and
        Adam's update is per coordinate, so each instance's path is the one it would take alone.
        """
        lam = self.lam if lam is None else float(lam)
        steps = self.ml_steps if steps is None else int(steps)
        decoder = self.model.decoder
        was_training = decoder.training
        decoder.eval()
        with torch.inference_mode(False), torch.enable_grad():
            occ, fr = occupied.clone(), free.clone()
            if init is None:
                z = torch.zeros(len(occ), self.model.latent, device=occ.device, requires_grad=True)
            else:
                z = init.detach().clone().float().requires_grad_(True)
            opt = torch.optim.Adam([z], lr=self.ml_lr if lr is None else float(lr))
            params = [p.requires_grad for p in decoder.parameters()]
            for p in decoder.parameters():
                p.requires_grad_(False)
            try:
                dtype = next(decoder.parameters()).dtype
                for _ in range(steps):
                    loss = (observed_nll(decoder(z.to(dtype)).float(), occ, fr, float(self.config["log_var"]))
                            + lam * 0.5 * (z**2).sum(1)).sum()
                    opt.zero_grad(set_to_none=True)
                    loss.backward()
                    opt.step()
            finally:
                for p, flag in zip(decoder.parameters(), params):
                    p.requires_grad_(flag)
                decoder.train(was_training)
        return z.detach()


@register("aml_ml")
class AMLMaximumLikelihood(AML):
    """The ML baseline of AML (Eq. 4): same prior and objective, ``z`` optimised per instance.

    Loads AML's checkpoints (the decoder and lambda); the amortized encoder is not used.
    """

    inference = "ml"
    weights_name = "aml"
