"""Fuzz corpus, checkpoints and training data: tampered dtypes, hyper-parameters, keys, JSON
depth, random config and weights bytes; an instance cache with NaN points.

Every case is a :class:`CheckpointError` / ``ERROR pcc:`` naming the file — nothing is
unpickled, nothing is cast or defaulted silently.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from conftest import assert_named_failure, run_cli
from fuzz_support import RANDOM_JSON_BYTES, small_frames
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from safetensors.torch import load_file, save_file

from pcc_ros.data.instances import ExtractConfig, extract_instances
from pcc_ros.errors import CheckpointError
from pcc_ros.models.checkpoint import load_checkpoint, sha256_file
from pcc_ros.models.registry import load_completer

SHIPPED = Path(__file__).resolve().parents[1] / "pcc_ros" / "weights" / "pointpncnet"


def tampered(tmp: Path, edit_config=None, edit_state=None, config_text=None) -> Path:
    """A copy of the shipped checkpoint with its config / tensors edited and the hash and size
    re-recorded (so only the validation under test can catch it)."""
    import torch  # noqa: F401  (safetensors.torch needs it)

    weights, config_path = tmp / "m.safetensors", tmp / "m.json"
    state = load_file(f"{SHIPPED}.safetensors")
    config = json.loads(Path(f"{SHIPPED}.json").read_text())
    if edit_state:
        state = edit_state(state)
    if edit_config:
        edit_config(config)
    save_file(state, str(weights))
    config["sha256"], config["size_bytes"] = sha256_file(weights), weights.stat().st_size
    config_path.write_text(config_text(config) if config_text else json.dumps(config))
    return weights


def _nested(depth: int):
    return lambda config: json.dumps(config).replace('"@N@"', "[" * depth + "]" * depth)


CASES = {
    "float16 tensors": (dict(edit_state=lambda s: {k: v.half() for k, v in s.items()}), "dtypes do not match"),
    "one int32 tensor": (dict(edit_state=lambda s: {k: (v.int() if i == 0 else v) for i, (k, v) in
                                                     enumerate(sorted(s.items()))}), "int32"),
    "float16 without a dtype record": (dict(edit_state=lambda s: {k: v.half() for k, v in s.items()},
                                            edit_config=lambda c: c.pop("dtypes")), "do not fit the model"),
    "missing hyper-parameter": (dict(edit_config=lambda c: c["hyper_parameters"].pop("attention_hidden")),
                                r"lacks hyper-parameters \['attention_hidden'\]"),
    "unknown hyper-parameter": (dict(edit_config=lambda c: c["hyper_parameters"].update(bogus=1)),
                                "unknown to backend"),
    "extra top-level key": (dict(edit_config=lambda c: c.update(pickle_me="x")), "unknown checkpoint config keys"),
    "deeply nested JSON": (dict(edit_config=lambda c: c.update(training="@N@"), config_text=_nested(100_000)),
                           "nested too deeply"),
    "moderately nested JSON": (dict(edit_config=lambda c: c.update(training="@N@"), config_text=_nested(40)),
                               "nested more than 32 levels"),
}


@pytest.mark.parametrize("case", list(CASES))
def test_tampered_checkpoints_are_refused_by_name(tmp_path, caplog, case):
    kwargs, pattern = CASES[case]
    weights = tampered(tmp_path, **kwargs)
    with pytest.raises(CheckpointError, match=pattern) as info:
        load_completer("pointpncnet", str(weights))
    assert str(tmp_path) in str(info.value)


def test_tampered_checkpoint_through_the_cli(tmp_path, caplog):
    weights = tampered(tmp_path, edit_state=lambda s: {k: v.half() for k, v in s.items()})
    rc, text = run_cli(["replay", tmp_path / "nothing", "--out", tmp_path / "o", "--checkpoint", weights], caplog)
    assert_named_failure(rc, text, str(weights), output=tmp_path / "o")


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=RANDOM_JSON_BYTES)
def test_random_config_bytes_are_a_checkpoint_error(tmp_path, data):
    shutil.copy(f"{SHIPPED}.safetensors", tmp_path / "m.safetensors")
    (tmp_path / "m.json").write_bytes(data)
    with pytest.raises(CheckpointError):
        load_checkpoint(tmp_path / "m")


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(position=st.floats(0, 1, exclude_max=True), mask=st.integers(1, 255), cut=st.booleans())
def test_damaged_weights_are_a_checkpoint_error(tmp_path, position, mask, cut):
    shutil.copy(f"{SHIPPED}.json", tmp_path / "m.json")
    data = bytearray(Path(f"{SHIPPED}.safetensors").read_bytes())
    at = int(position * len(data))
    if cut:
        data = data[:at]
    else:
        data[at] ^= mask
    (tmp_path / "m.safetensors").write_bytes(bytes(data))
    with pytest.raises(CheckpointError, match=r"m\.safetensors"):
        load_checkpoint(tmp_path / "m")


def test_training_on_a_cache_with_nan_points_names_the_shard(tmp_path, caplog):
    cache = tmp_path / "cache"
    extract_instances(small_frames(3), cache, ExtractConfig(ground_margin=0.0), progress=False)
    shard = next((cache / "shards").glob("*.points.npy"))
    points = np.load(shard)
    points[5] = np.nan
    np.save(shard, points)
    out = tmp_path / "run"
    rc, text = run_cli(["train", "pointpncnet", "--data", cache, "--out", out, "--iterations", "1",
                        "--threads", "1", "--no-progress"], caplog)
    assert_named_failure(rc, text, str(shard), "non-finite point")
