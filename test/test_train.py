"""`pcc train`: the generic loop, resumable checkpoints, validation, errors."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from conftest import assert_named_failure, run_cli

from pcc_ros.cli.main import main
from pcc_ros.errors import ConfigError
from pcc_ros.models import load_completer
from pcc_ros.models.checkpoint import load_config
from pcc_ros.workflows.train import learning_rate, load_recipe, optimizer_tensors, parse_options, restore_optimizer


def _argv(tiny_cache, out, *extra):
    return ["train", "pointpncnet", "--data", str(tiny_cache), "--out", str(out), "--batch-size", "4",
            "--val-split", "test", "--val-instances", "6", "--val-every", "2", "--checkpoint-every", "2",
            "--no-progress", "--device", "cpu", "--option", "loss_points=64", "--option", "local_loss_points=8",
            *extra]


@pytest.mark.slow
def test_train_validate_checkpoint_and_resume(tiny_cache, tmp_path, capsys, caplog):
    out = tmp_path / "run"
    assert main(_argv(tiny_cache, out, "--iterations", "4")) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["step"] == 4
    for name in ("pointpncnet.safetensors", "pointpncnet.json", "resume.safetensors", "resume.json",
                 "log.jsonl", "training.png"):
        assert (out / name).is_file(), name
    records = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    vals = [r for r in records if "val_cd_l1" in r]
    assert [r["step"] for r in vals] == [2, 4] and all(r["val_cd_l1"] > 0 for r in vals)
    assert [r["step"] for r in records if "loss" in r] == [4]
    config = load_config(out / "pointpncnet.json")
    best = min(vals, key=lambda r: r["val_cd_l1"])  # the shipped weights are the best by validation
    assert config["training"]["selected_step"] == best["step"] == config["training"]["steps"]
    assert config["training"]["validation_reference"] == "ground_truth"
    assert config["training"]["selected_by"] == "val_cd_l1"
    assert config["training"]["recipe"]["drop_prob"] == 0.2
    assert config["metrics"]["val_cd_l1"] == best["val_cd_l1"]
    # Not only what the run wrote about itself: the weights in the file, scored again on the same
    # validation instances, give the recorded figure (the file holds the weights that scored it).
    from pcc_ros.data.instances import InstanceCache
    from pcc_ros.workflows.train import validate, validation_instances

    instances, _ = validation_instances(InstanceCache.load(tiny_cache), "test", 6, 0)
    rescored = validate(load_completer("pointpncnet", out / "pointpncnet.safetensors", device="cpu"), instances, 0)
    assert rescored["val_cd_l1"] == pytest.approx(best["val_cd_l1"], rel=1e-4)
    assert config["training"]["machine"]["cpu_count"] >= 1 and config["training"]["real_data"]["share"] == 0.0
    last = load_config(out / "pointpncnet_last.json")
    assert last["training"]["steps"] == 4 and last["metrics"]["val_cd_l1"] == vals[-1]["val_cd_l1"]
    completer = load_completer("pointpncnet", out / "pointpncnet.safetensors", device="cpu")
    assert completer.complete([np.random.default_rng(0).normal(size=(50, 3)) * 0.2])[0].shape == (2048, 3)

    # a second run into the same directory must be explicit
    assert_named_failure(*run_cli(_argv(tiny_cache, out, "--iterations", "4"), caplog), out,
                         "already holds a training run", "pass --resume")
    # resuming continues the step counter and the log
    assert main(_argv(tiny_cache, out, "--iterations", "8", "--resume")) == 0
    assert json.loads(capsys.readouterr().out)["step"] == 8
    resume = load_config(out / "resume.json")["resume"]
    assert resume["step"] == 8 and resume["lr_decay_every"] == 1  # kept from the 4-step run, not 8 // 4
    records = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in records if "val_cd_l1" in r] == [2, 4, 6, 8]
    # resuming with other settings is refused
    assert_named_failure(*run_cli(_argv(tiny_cache, out, "--iterations", "10", "--resume", "--lr", "1e-2"), caplog),
                         "--resume with different settings than the saved run", "'lr': (0.0005, 0.01)")
    assert_named_failure(*run_cli(_argv(tiny_cache, out, "--iterations", "10", "--resume", "--config", "paper"),
                                  caplog), out / "resume.safetensors", "made with another model config")


def test_real_scans_are_mixed_at_the_requested_share(tiny_cache, tmp_path, caplog):
    out = tmp_path / "mixed"
    argv = [*_argv(tiny_cache, out, "--iterations", "2"), "--val-instances", "0", "--real-data", str(tiny_cache),
            "--real-share", "0.25"]
    assert main(argv) == 0
    mixing = load_config(out / "pointpncnet.json")["training"]["real_data"]
    assert mixing["share_requested"] == 0.25 and mixing["repeats"] >= 1 and mixing["share"] > 0  # tiny: 1 repeat
    assert mixing["groups"] >= 1 and str(tiny_cache) in mixing["caches"]
    # A share outside (0, 1) is refused for itself (into a fresh --out: not "already holds a run").
    fresh = [str(tmp_path / "fresh") if a == str(out) else a for a in argv[:-1]]
    assert_named_failure(*run_cli([*fresh, "1.5"], caplog), "--real-share must be in (0, 1), got 1.5")


@pytest.mark.slow
def test_init_from_a_checkpoint_is_recorded_and_validated_at_step_0(tiny_cache, tmp_path, caplog):
    first = tmp_path / "first"
    assert main(_argv(tiny_cache, first, "--iterations", "2")) == 0
    out = tmp_path / "finetune"
    assert main(_argv(tiny_cache, out, "--iterations", "2", "--init", str(first / "pointpncnet_last.safetensors"))) == 0
    config = load_config(out / "pointpncnet.json")
    assert config["training"]["init"]["path"].endswith("pointpncnet_last.safetensors")
    records = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    start = [r for r in records if r["step"] == 0]
    assert start and start[0]["val_cd_l1"] == pytest.approx(
        load_config(first / "pointpncnet_last.json")["metrics"]["val_cd_l1"], rel=1e-5)  # the same weights
    assert config["training"]["selected_step"] == 2  # step 0 (the initial weights) is never "selected"
    bad = tmp_path / "bad"
    argv = _argv(tiny_cache, bad, "--iterations", "2", "--init", str(tmp_path / "missing.safetensors"))
    assert_named_failure(*run_cli(argv, caplog), tmp_path / "missing.safetensors", "checkpoint weights not found",
                         output=bad)


def test_no_inpainting_ablation_is_recorded(tiny_cache, tmp_path):
    out = tmp_path / "ablation"
    assert main([*_argv(tiny_cache, out, "--iterations", "2", "--no-inpainting"), "--val-instances", "0"]) == 0
    assert load_config(out / "pointpncnet.json")["training"]["recipe"]["drop_prob"] == 0.0


def test_optimizer_state_round_trip():
    torch.manual_seed(0)
    net = torch.nn.Linear(4, 3)
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    for _ in range(3):
        opt.zero_grad()
        net(torch.randn(8, 4)).pow(2).sum().backward()
        opt.step()
    tensors, meta = optimizer_tensors(opt)
    meta = json.loads(json.dumps(meta))  # it must survive the JSON config
    fresh = torch.optim.Adam(net.parameters(), lr=1e-3)
    restore_optimizer(fresh, tensors, meta, source="test")
    a, b = opt.state_dict(), fresh.state_dict()
    assert a["param_groups"] == b["param_groups"]
    for pid in a["state"]:
        for key, value in a["state"][pid].items():
            assert torch.equal(torch.as_tensor(value), torch.as_tensor(b["state"][pid][key]))


def test_options_schedule_and_recipe_errors():
    assert parse_options(["views=2", "beta=0.5", "name=x"]) == {"views": 2, "beta": 0.5, "name": "x"}
    with pytest.raises(ConfigError):
        parse_options(["views"])
    assert learning_rate(5e-4, 0, 100) == 5e-4
    assert learning_rate(5e-4, 250, 100) == pytest.approx(1.25e-4)
    with pytest.raises(ConfigError, match="unknown completion backend"):
        load_recipe("nonexistent", "default", {})
    with pytest.raises(ConfigError, match="cannot be trained"):
        load_recipe("mirror", "default", {})
    with pytest.raises(ConfigError, match="invalid training options"):
        load_recipe("pointpncnet", "default", {"bogus": 1})


@pytest.mark.parametrize(("backend", "options", "message"), [
    ("pointpncnet", {"views": "abc"}, r"--option views=\"abc\" must be int"),
    ("pointpncnet", {"views": 2.5}, r"--option views=2.5 must be int"),
    ("pointpncnet", {"box_aspect": 1}, r"--option box_aspect=1 must be bool"),
    ("pointpncnet", {"input_points": "many"}, r"--option input_points=\"many\" must be int or null"),
    ("trapcc", {"real_share": "half"}, r"invalid training options \['real_share'\]"),  # its own range check
    ("trapcc", {"whole_loss_points": "two"}, r"--option whole_loss_points=\"two\" must be int"),
    ("aml", {"real_repeat": "abc"}, r"invalid training options \['real_repeat'\]"),
])
def test_a_training_option_of_the_wrong_type_is_refused_naming_it(backend, options, message):
    """`pcc train pointpncnet --option views=abc` was an internal TypeError at the first step."""
    with pytest.raises(ConfigError, match=message):
        load_recipe(backend, "default", options)


def test_training_options_of_the_right_type_pass():
    recipe = load_recipe("pointpncnet", "default", {"views": 2, "drop_prob": 0, "input_points": None,
                                                    "box_aspect": True, "held_out": ["a"]})
    assert recipe.options.views == 2 and recipe.options.drop_prob == 0


@pytest.mark.slow
def test_torchrun_two_processes_gloo(tiny_cache, tmp_path):
    """DistributedDataParallel under torchrun (two CPU processes, gloo): rank 0 writes one run."""
    import shutil
    import subprocess
    import sys
    from pathlib import Path

    torchrun = Path(sys.executable).with_name("torchrun")
    if not torchrun.exists():
        torchrun = shutil.which("torchrun")
    if not torchrun:
        pytest.skip("torchrun not installed")
    out = tmp_path / "ddp"
    argv = _argv(tiny_cache, out, "--iterations", "4", "--threads", "1")
    proc = subprocess.run(
        [str(torchrun), "--nproc-per-node", "2", "-m", "pcc_ros.cli", *argv],
        capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout.count('"step": 4') >= 1  # rank 0's summary only
    config = load_config(out / "pointpncnet_last.json")
    assert config["training"]["world_size"] == 2 and config["training"]["steps"] == 4
    assert load_config(out / "pointpncnet.json")["training"]["selected_step"] in (2, 4)  # best by validation
    assert load_config(out / "resume.json")["resume"]["step"] == 4


def test_every_trainable_backend_states_the_recipe_contract():
    """`pcc train` drives a declared interface (models.recipe.TrainingRecipe), never probes a recipe."""
    import ast

    import pcc_ros.workflows.train
    from pcc_ros.models import BACKENDS, get_backend
    from pcc_ros.models.recipe import TrainingRecipe

    trainable = [name for name in BACKENDS if get_backend(name).recipe_factory is not None]
    assert set(trainable) >= {"pointpncnet", "trapcc", "aml", "aml_ml"}
    for name in trainable:
        recipe = load_recipe(name, "default", {})
        assert isinstance(recipe, TrainingRecipe) and recipe.kit is not None
    tree = ast.parse(open(pcc_ros.workflows.train.__file__, encoding="utf-8").read())
    probes = [f"line {node.lineno}: {ast.unparse(node)}" for node in ast.walk(tree)
              if isinstance(node, ast.Call) and getattr(node.func, "id", "") in ("hasattr", "getattr")
              and "recipe" in ast.unparse(node.args[0])]
    assert not probes, probes


def test_max_minutes_stops_the_loop_and_saves_as_at_the_end(tiny_cache, tmp_path, caplog):
    out = tmp_path / "budget"
    with caplog.at_level("INFO", logger="pcc.train"):
        assert main([*_argv(tiny_cache, out, "--iterations", "1000"), "--val-instances", "0",
                     "--max-minutes", "0"]) == 0  # spent before the first step
    assert "--max-minutes 0.0 spent at step 0 of 1000" in caplog.text
    config = load_config(out / "pointpncnet.json")
    assert config["training"]["steps"] == 0 and (out / "pointpncnet_last.safetensors").is_file()
    load_completer("pointpncnet", out / "pointpncnet.safetensors", device="cpu")  # a usable checkpoint
