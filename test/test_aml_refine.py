"""AML's amortised-then-refined inference: the encoder's code as the start of Eq. 4's optimisation."""

from __future__ import annotations

import json
import shutil
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from pcc_ros.errors import CheckpointError, ConfigError
from pcc_ros.models import load_completer
from pcc_ros.models.aml import observed_nll, select_refinement
from pcc_ros.models.base import SceneContext
from pcc_ros.models.registry import default_checkpoint
from pcc_ros.types import Boxes


def _van(seed: int, n: int = 400) -> tuple[np.ndarray, SceneContext]:
    """A canonical partial scan of a boxy van seen from its rear-right (rear face and right side:
    a car the mean code does not explain), and its scene context (box 4.8 x 1.9 x 2.0 m)."""
    rng = np.random.default_rng(seed)
    half = np.array([0.5, 0.2, 0.21])  # box half-extents in box lengths
    rear = np.c_[np.full(n // 2, -half[0]), rng.uniform(-1, 1, (n // 2, 2)) * half[1:]]
    side = np.c_[rng.uniform(-1, 1, n - n // 2) * half[0], np.full(n - n // 2, -half[1]),
                 rng.uniform(-1, 1, n - n // 2) * half[2]]
    cloud = np.r_[rear, side].astype(np.float32)
    box = Boxes(np.array([[-8.0, -6.0, 0.0]]), np.array([[4.8, 1.9, 2.0]]), np.array([0.0]),
                np.array(["Van"], object))
    return cloud, SceneContext(box=box, neighbour_boxes=box[np.array([], int)])


def _grids(aml, n: int = 3):
    scans = [_van(s, 200 + 150 * s) for s in range(n)]
    with torch.inference_mode():
        x, _ = aml.observe([c for c, _ in scans], [ctx for _, ctx in scans])
    return x, [c for c, _ in scans], [ctx for _, ctx in scans]


def _objective(aml, x: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
    """Eq. 4's per-instance objective: observed-voxel NLL + lambda ||z||^2 / 2."""
    with torch.inference_mode():
        decoded = aml.model.decoder(z)
        return observed_nll(decoded, x[:, 0] > 0.5, x[:, 1] > 0.5, float(aml.config["log_var"])) \
            + aml.lam * 0.5 * (z**2).sum(1)


@pytest.fixture(scope="module")
def aml():
    torch.manual_seed(0)
    return load_completer("aml", device="cpu")  # the shipped weights: a prior that means something


def test_refinement_lowers_the_objective_from_the_encoders_code(aml):
    x, _, _ = _grids(aml)
    with torch.inference_mode():
        z0 = aml.model.encoder(x)
    z = aml.fit_latent(x[:, 0] > 0.5, x[:, 1] > 0.5, steps=8, init=z0, lr=0.05)
    before, after = _objective(aml, x, z0), _objective(aml, x, z)
    assert (after < before).all(), (before, after)
    assert not torch.equal(z, z0) and z0.requires_grad is False  # the encoder's code is not modified in place


def test_zero_refine_steps_gives_the_encoders_output_exactly(aml):
    x, clouds, contexts = _grids(aml)
    with torch.inference_mode():
        np.testing.assert_array_equal(aml.latent_codes(x).numpy(), aml.model.encoder(x).numpy())
        _, decoded = aml.model(x)
    expected = aml.decode_points(decoded, clouds, aml.aspects(contexts))
    assert aml.refine_steps == 0
    for a, b in zip(aml.complete(clouds, contexts), expected):
        np.testing.assert_array_equal(a, b)
    refined = load_completer("aml", device="cpu", refine_steps=3)
    assert any(not np.array_equal(a, b) for a, b in zip(refined.complete(clouds, contexts), expected))


def test_batched_refinement_equals_per_instance(aml):
    x, _, _ = _grids(aml)
    occ, free = x[:, 0] > 0.5, x[:, 1] > 0.5
    with torch.inference_mode():
        z0 = aml.model.encoder(x)
    batched = aml.fit_latent(occ, free, steps=4, init=z0, lr=0.15)
    alone = torch.cat([aml.fit_latent(occ[i:i + 1], free[i:i + 1], steps=4, init=z0[i:i + 1], lr=0.15)
                       for i in range(len(x))])
    torch.testing.assert_close(batched, alone, rtol=1e-4, atol=1e-4)


def test_refinement_settings_from_the_checkpoint_and_run_time(tmp_path):
    shipped = default_checkpoint("aml")
    weights = shutil.copy(shipped, tmp_path / "aml.safetensors")
    config = json.loads(shipped.with_suffix(".json").read_text())
    config["training"].update(refine_steps=7, refine_lr=0.05)
    (tmp_path / "aml.json").write_text(json.dumps(config))
    loaded = load_completer("aml", weights, device="cpu")
    assert (loaded.refine_steps, loaded.refine_lr) == (7, 0.05)
    assert load_completer("aml", weights, device="cpu", refine_steps=0).refine_steps == 0  # run-time option wins
    with pytest.raises(ConfigError, match="refine_steps"):
        load_completer("aml", weights, device="cpu", refine_steps=-1)
    with pytest.raises(ConfigError, match="refine_lr"):
        load_completer("aml", weights, device="cpu", refine_lr=0.0)
    config["training"]["refine_steps"] = "ten"
    (tmp_path / "aml.json").write_text(json.dumps(config))
    with pytest.raises(CheckpointError, match="refine"):
        load_completer("aml", weights, device="cpu")


def test_select_refinement_scores_every_grid_point(aml):
    rng = np.random.default_rng(1)
    instances = []
    for s in range(2):
        cloud, ctx = _van(s, 200)
        reference = (rng.uniform(-0.5, 0.5, (600, 3)) * [1, 0.4, 0.42]).astype(np.float32)
        instances.append(SimpleNamespace(partial=cloud, context=ctx, reference=reference, length=4.8))
    out = select_refinement(aml, instances, steps=[0, 2], lrs=[0.05, 0.15], seed=0)
    assert set(out["table"]) == {"0@0", "2@0.05", "2@0.15"}
    assert out["chosen"] in out["table"] and out["refine_steps"] in (0, 2)
    assert all(np.isfinite(v) and v > 0 for v in out["table"].values())
    assert aml.refine_steps == 0  # the completer's own setting is restored
