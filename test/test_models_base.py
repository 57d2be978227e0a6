"""Completer interface, registry, devices, baselines and checkpoint I/O."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from pcc_ros.errors import CheckpointError, ConfigError, DataError
from pcc_ros.models import (
    Completer,
    SceneContext,
    TorchCompleter,
    available,
    create,
    get_backend,
    load_completer,
    register,
    resample_cloud,
    select_device,
)
from pcc_ros.models.checkpoint import load_checkpoint, load_config, save_checkpoint
from pcc_ros.types import Boxes


@register("tiny_test")
class TinyCompleter(TorchCompleter):
    """A real (small) network: per-point MLP on a content-seeded fixed-size resample."""

    @classmethod
    def default_config(cls):
        return {"num_points": 32, "hidden": 8}

    def build_model(self):
        h = self.config["hidden"]
        return torch.nn.Sequential(torch.nn.Linear(3, h), torch.nn.ReLU(), torch.nn.Dropout(0.5), torch.nn.Linear(h, 3))

    def forward_batch(self, clouds, contexts):
        self.batches_seen.append(len(clouds))
        x = np.stack([resample_cloud(c, self.config["num_points"]) for c in clouds])
        y = self.model(torch.from_numpy(x).to(self.device))
        assert torch.is_inference_mode_enabled()
        return list(y.cpu().numpy())

    def __init__(self, *args, **kwargs):
        self.batches_seen = []
        super().__init__(*args, **kwargs)


def _clouds(seed=0, sizes=(5, 50, 200)):
    rng = np.random.default_rng(seed)
    return [rng.normal(size=(n, 3)).astype(np.float32) for n in sizes]


def test_registry_lists_baselines_and_rejects_unknown():
    names = available()
    assert {"input", "densify", "mirror", "tiny_test"} <= set(names)
    with pytest.raises(ConfigError, match="unknown completion backend 'nope'"):
        create("nope")
    with pytest.raises(ConfigError, match="bad options"):
        create("input", num_points=3)
    with pytest.raises(ConfigError, match="unknown option"):
        create("tiny_test", device="cpu", depth=3)


def test_register_refuses_name_clash_and_non_completer():
    with pytest.raises(ValueError, match="already registered"):

        @register("input")
        class Other(Completer):
            def _complete(self, clouds, contexts):
                return clouds

    with pytest.raises(TypeError):
        register("thing")(dict)


def test_select_device():
    assert select_device("cpu").type == "cpu"
    assert select_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")
    with pytest.raises(ConfigError, match="invalid device"):
        select_device("gpu7")
    if not torch.cuda.is_available():
        with pytest.raises(ConfigError, match="CUDA is not available"):
            select_device("cuda")


def test_complete_validates_inputs():
    completer = create("input")
    with pytest.raises(DataError, match="partial cloud 1 is empty"):
        completer.complete([np.zeros((3, 3)), np.zeros((0, 3))])
    with pytest.raises(DataError, match="partial cloud 0 has non-finite"):
        completer.complete([np.array([[0, 0, np.nan]])])
    with pytest.raises(DataError, match="expected shape"):
        completer.complete([np.zeros((4, 2))])
    with pytest.raises(DataError, match="2 scene contexts for 1 clouds"):
        completer.complete([np.zeros((3, 3))], [None, None])
    assert completer.complete([]) == []
    # A (B, N, 3) batch and extra columns (intensity) are accepted.
    out = completer.complete(np.ones((2, 4, 4), dtype=np.float64))
    assert [o.shape for o in out] == [(4, 3), (4, 3)] and out[0].dtype == np.float32


def test_input_and_mirror_baselines():
    rng = np.random.default_rng(1)
    half = rng.uniform([-0.5, 0.05, -0.2], [0.5, 0.2, 0.2], size=(100, 3)).astype(np.float32)
    (out,) = create("input").complete([half])
    np.testing.assert_array_equal(out, half)
    (mirrored,) = create("mirror").complete([half])
    assert mirrored.shape == (200, 3)
    np.testing.assert_array_equal(mirrored[:100], half)
    np.testing.assert_array_equal(mirrored[100:], half * [1, -1, 1])
    # The mirror of a symmetric car reproduces it: the set of points is unchanged.
    symmetric = np.concatenate([half, half * np.float32([1, -1, 1])])
    (again,) = create("mirror").complete([symmetric])
    as_set = lambda a: {tuple(p) for p in np.round(a, 6)}  # noqa: E731
    assert as_set(again) == as_set(symmetric)


def test_densify_samples_inside_neighbourhood_ellipsoids():
    # A flat patch (z = 0): every neighbourhood covariance has a zero z-eigenvalue,
    # so the densified points must stay on the plane and near the patch.
    rng = np.random.default_rng(2)
    patch = np.column_stack([rng.uniform(-0.3, 0.3, 300), rng.uniform(-0.1, 0.1, 300), np.zeros(300)])
    densify = create("densify", num_points=1000, seed=3)
    (out,) = densify.complete([patch.astype(np.float32)])
    assert out.shape == (1000, 3)
    assert np.abs(out[:, 2]).max() < 1e-5
    assert out[:, 0].min() > -0.4 and out[:, 0].max() < 0.4
    # Not a copy of the input: new positions.
    assert len({tuple(p) for p in np.round(out, 6)} & {tuple(p) for p in np.round(patch, 6)}) < 10
    # Deterministic, and independent of what else is in the batch.
    (again,) = densify.complete([patch.astype(np.float32)])
    np.testing.assert_array_equal(out, again)
    batched = densify.complete([np.ones((5, 3), np.float32), patch.astype(np.float32)])
    np.testing.assert_array_equal(out, batched[1])
    # Tiny inputs still work (one point: its samples collapse on it).
    (single,) = densify.complete([np.float32([[0.1, 0.2, 0.3]])])
    np.testing.assert_allclose(single, np.tile([0.1, 0.2, 0.3], (1000, 1)), atol=1e-6)


def test_densify_sample_spread_matches_covariance():
    # 10 points: every point's 10-NN neighbourhood is the whole cloud, so all ellipsoids share
    # the cloud's covariance C; each sample s must lie in some {x: (x-p)^T C^-1 (x-p) <= 1}
    # and the samples must fill that ellipsoid (mean squared Mahalanobis radius 3/5 for a
    # uniform ball in 3-D).
    rng = np.random.default_rng(5)
    cloud = (rng.normal(size=(10, 3)) * [0.3, 0.1, 0.02]).astype(np.float32)
    (out,) = create("densify", num_points=5000, k=10).complete([cloud])
    c = np.cov(cloud.astype(np.float64).T, bias=True)
    inv = np.linalg.inv(c)
    diff = out[:, None, :].astype(np.float64) - cloud[None, :, :]  # (M, 10, 3)
    maha = np.einsum("mni,ij,mnj->mn", diff, inv, diff)
    assert maha.min(axis=1).max() <= 1 + 1e-3
    owner = np.arange(5000) % 10  # round-robin owners when N <= num_points
    r2 = maha[np.arange(5000), owner]
    assert abs(r2.mean() - 3 / 5) < 0.03


def test_torch_completer_batches_and_is_deterministic():
    completer = create("tiny_test", device="cpu", batch_size=2)
    clouds = _clouds()
    out = completer.complete(clouds)
    assert completer.batches_seen == [2, 1]
    assert [o.shape for o in out] == [(32, 3)] * 3
    assert not completer.model.training
    completer.model.train()  # someone left it in train mode: complete() must still be eval
    again = completer.complete(clouds[::-1])
    for a, b in zip(out, again[::-1]):
        np.testing.assert_array_equal(a, b)


def test_checkpoint_round_trip(tmp_path):
    completer = create("tiny_test", device="cpu", hidden=6)
    path = completer.save(tmp_path / "ck.safetensors", training={"instances": 12, "seed": 4}, metrics={"cd_l1_m": 0.1})
    config = load_config(path)
    assert config["backend"] == "tiny_test"
    assert config["hyper_parameters"] == {"num_points": 32, "hidden": 6}
    assert config["points"] == {"num_points": 32}
    assert config["training"]["instances"] == 12 and config["metrics"] == {"cd_l1_m": 0.1}
    assert config["tensors"]["0.weight"] == [6, 3]
    assert "git_revision" in config
    loaded = load_completer("tiny_test", tmp_path / "ck", device="cpu", batch_size=1)
    assert loaded.config["hidden"] == 6 and loaded.checkpoint_config["training"]["seed"] == 4
    for a, b in zip(completer.complete(_clouds()), loaded.complete(_clouds())):
        np.testing.assert_array_equal(a, b)


@pytest.fixture
def saved(tmp_path):
    completer = create("tiny_test", device="cpu")
    return completer.save(tmp_path / "ck.safetensors"), tmp_path / "ck.json"


def test_checkpoint_missing_files(tmp_path, saved):
    weights, config = saved
    with pytest.raises(CheckpointError, match="weights not found"):
        load_checkpoint(tmp_path / "other.safetensors")
    config.unlink()
    with pytest.raises(CheckpointError, match="config not found"):
        load_checkpoint(weights)


def test_checkpoint_truncated_and_corrupt(saved):
    weights, _ = saved
    data = weights.read_bytes()
    weights.write_bytes(data[: len(data) - 40])
    with pytest.raises(CheckpointError, match="truncated"):
        load_checkpoint(weights)
    flipped = bytearray(data)
    flipped[-5] ^= 0xFF
    weights.write_bytes(bytes(flipped))
    with pytest.raises(CheckpointError, match="corrupt"):
        load_checkpoint(weights)
    # Without the hash check, a broken header is still refused by the safetensors parser.
    garbage = b"\xff" * 8 + data[8:]
    weights.write_bytes(garbage)
    with pytest.raises(CheckpointError, match="cannot read safetensors"):
        load_checkpoint(weights, verify_hash=False)


def test_checkpoint_bad_config(saved):
    weights, config = saved
    text = config.read_text()
    config.write_text(text[:50])
    with pytest.raises(CheckpointError, match="not a valid JSON"):
        load_checkpoint(weights)
    data = json.loads(text)
    del data["tensors"]
    config.write_text(json.dumps(data))
    with pytest.raises(CheckpointError, match="lacks"):
        load_checkpoint(weights)
    data = json.loads(text)
    data["tensors"]["0.weight"] = [9, 3]
    config.write_text(json.dumps(data))
    with pytest.raises(CheckpointError, match=r"0.weight: config \[9, 3\] vs file \[8, 3\]"):
        load_checkpoint(weights)


def test_checkpoint_mismatched_model(tmp_path, saved):
    weights, config = saved
    # Config edited to another architecture: the weights no longer fit the model built from it.
    data = json.loads(config.read_text())
    data["hyper_parameters"]["hidden"] = 16
    config.write_text(json.dumps(data))
    with pytest.raises(CheckpointError, match="do not fit the model"):
        load_completer("tiny_test", weights, device="cpu")
    data["hyper_parameters"]["hidden"] = 8
    data["hyper_parameters"]["depth"] = 2
    config.write_text(json.dumps(data))
    with pytest.raises(CheckpointError, match="unknown to backend"):
        load_completer("tiny_test", weights, device="cpu")
    data["hyper_parameters"].pop("depth")
    data["backend"] = "input"
    config.write_text(json.dumps(data))
    with pytest.raises(CheckpointError, match="not 'tiny_test'"):
        load_completer("tiny_test", weights, device="cpu")


def test_checkpoint_rejects_nan_weights(tmp_path):
    state = {"w": torch.tensor([1.0, float("nan")])}
    path = save_checkpoint(tmp_path / "nan", state, {"backend": "x", "hyper_parameters": {}})
    with pytest.raises(CheckpointError, match="NaN"):
        load_checkpoint(path)


def test_load_completer_defaults():
    with pytest.raises(CheckpointError, match="no default checkpoint shipped for backend 'tiny_test'"):
        load_completer("tiny_test", device="cpu")
    with pytest.raises(ConfigError, match="has no weights"):
        load_completer("mirror", checkpoint="x.safetensors")
    assert isinstance(load_completer("input"), Completer)


def test_scene_context_neighbours():
    boxes = Boxes(
        center=[[10, 0, 0], [12, 0, 0], [30, 0, 0], [10, 5, 0], [0, -3, 0]],
        size=[[4, 2, 1.5]] * 5,
        yaw=[np.pi / 2, 0, 0, 0, 0],
        track_id=["a", "b", "c", "d", "e"],
    )
    clouds = [np.full((3 + i, 3), i, np.float32) for i in range(5)]
    contexts = SceneContext.from_frame(boxes, clouds)
    assert len(contexts) == 5 and len(contexts[0].neighbour_boxes) == 4
    near = contexts[0].nearest(k=2, radius=8.0)
    assert list(near.neighbour_boxes.track_id) == ["b", "d"]
    assert [len(p) for p in near.neighbour_points] == [4, 6]
    # Box "a" faces +y; "b" is 2 m to its right (-y in its canonical frame), length 4 -> 0.5.
    np.testing.assert_allclose(near.neighbour_centres_canonical()[0], [0, -0.5, 0], atol=1e-6)
    assert len(contexts[0].nearest(k=3, radius=1.0).neighbour_boxes) == 0
    with pytest.raises(DataError):
        SceneContext.from_frame(boxes, clouds[:2])
    # Contexts pass through complete() unchanged for backends that ignore them.
    out = create("input").complete(clouds, contexts)
    assert len(out) == 5


def test_backend_table_names_every_registered_class_and_owns_recipes_and_presets():
    """The explicit table and the package's @register decorators agree (read with ast), and a
    backend's recipe and presets are found on its class."""
    import ast
    from pathlib import Path

    from pcc_ros.models import BACKENDS, get_backend
    from pcc_ros.workflows.train import load_recipe

    package = Path(__file__).resolve().parents[1] / "pcc_ros" / "models"
    decorated = {}
    for path in package.rglob("*.py"):  # backends may live in a subpackage (models/aml/)
        module = ".".join(("pcc_ros", "models", *path.relative_to(package).with_suffix("").parts))
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ClassDef):
                for deco in node.decorator_list:
                    if isinstance(deco, ast.Call) and getattr(deco.func, "id", "") == "register":
                        decorated[deco.args[0].value] = f"{module}:{node.name}"
    assert decorated == BACKENDS
    for name in BACKENDS:
        assert get_backend(name).name == name
    pointpncnet = get_backend("pointpncnet")
    assert set(pointpncnet.presets) >= {"default", "paper"} and get_backend("mirror").presets == {}
    recipe = load_recipe("pointpncnet", "default", {"inpainting": False})
    assert type(recipe).__name__ == "PointPnCNetRecipe" and recipe.describe()["drop_prob"] == 0.0
    assert type(load_recipe("aml_ml", "default", {})) is type(get_backend("aml").training_recipe())


def test_the_launch_file_help_names_every_backend():
    """``ros2 launch ... --show-args`` is where a user looks for the backends: it names the registry's."""
    import ast
    import re
    from pathlib import Path

    from pcc_ros.models import BACKENDS

    launch = Path(__file__).resolve().parents[1] / "launch" / "perception.launch.py"
    tree = ast.parse(launch.read_text(encoding="utf-8"))
    arguments = next(ast.literal_eval(node.value) for node in tree.body
                     if isinstance(node, ast.Assign) and getattr(node.targets[0], "id", "") == "ARGUMENTS")
    help_text = dict((name, text) for name, _, text in arguments)["backend"]
    assert set(BACKENDS) <= set(re.findall(r"\w+", help_text)), help_text


@pytest.mark.parametrize("name", ["pointpncnet", "trapcc", "aml", "aml_ml"])
def test_presets_sizes_and_recipes_come_from_the_base_class(name):
    """A backend states its PRESETS and its recipe; models.base checks sizes, builds defaults, trains."""
    cls = get_backend(name)
    assert cls.default_config() == {"size": "default", **cls.presets["default"]}
    with pytest.raises(ConfigError, match=r"unknown size 'huge'; choose from \['default'"):
        cls.training_recipe("huge")
    with pytest.raises(ConfigError, match="unknown size 'huge'"):
        create(name, device="cpu", size="huge")
    assert cls.recipe_factory is not None and type(cls.training_recipe()).__name__.endswith("Recipe")
    with pytest.raises(ConfigError, match="cannot be trained"):
        get_backend("mirror").training_recipe()


def test_worker_threads_log_as_the_node_whose_frame_they_complete():
    """``workers`` > 1: the shares completed on the pool's threads run in the calling thread's
    context, so a line logged there (aml's decoder warns per batch) is the line of the node at
    work (named after it, and said by its own rclpy logger), not a stray ``pcc_ros.models.*`` one."""
    import logging
    import threading

    from pcc_ros.runtime.node import working_for

    class Node:
        name = "pcc_ros.completion_node"

    class Logging(TinyCompleter):
        def forward_batch(self, clouds, contexts):
            logging.getLogger("pcc_ros.models.aml").warning("a decoder line")
            return super().forward_batch(clouds, contexts)

    seen = []

    class Keep(logging.Handler):
        def emit(self, record):
            seen.append((getattr(record, "pcc_node", record.name), record.threadName))

    handler, package = Keep(), logging.getLogger("pcc_ros")
    package.addHandler(handler)
    try:
        completer = Logging(device="cpu", batch_size=1, workers=2)
        with working_for(Node()):
            completer.complete(_clouds(sizes=(5, 9, 12, 20)))
    finally:
        package.removeHandler(handler)
    assert len(seen) == 4 and {name for name, _ in seen} == {"pcc_ros.completion_node"}, seen
    assert {thread for _, thread in seen} - {threading.current_thread().name}, seen  # some on a worker
