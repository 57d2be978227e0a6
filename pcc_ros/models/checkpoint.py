"""Checkpoints: safetensors weights + a JSON config beside them. Nothing is unpickled.

A checkpoint is two files with one stem: ``NAME.safetensors`` (tensors only, so loading
cannot execute code) and ``NAME.json``::

    {
      "format": "pcc_ros.checkpoint/1",
      "backend": "pointpncnet",
      "hyper_parameters": {...},          # exactly what the backend's constructor takes
      "points": {"input": 2048, ...},     # point counts (also in hyper_parameters when used)
      "training": {...},                  # data summary: dataset, split, instances, epochs, seed
      "metrics": {...},                   # validation figures, units named in the keys
      "tensors": {"name": [shape], ...},  # the manifest loading checks the file against
      "sha256": "...", "size_bytes": N,  # of the .safetensors file: catches truncation, flipped bytes
      "git_revision": "...", "pcc_ros_version": "...", "created": "..."
    }

Why the manifest and the hash: safetensors parses its header strictly, so a truncated
file is refused, but a corrupted tensor *payload* would load silently as garbage weights.
The SHA-256 catches that, and the manifest lets a mismatch (wrong backend version, edited
config) be reported tensor by tensor instead of as a bare torch ``load_state_dict`` error.

Every failure raises :class:`~pcc_ros.errors.CheckpointError` naming the file.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import subprocess
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from safetensors import SafetensorError

from pcc_ros import __version__, files
from pcc_ros.errors import CheckpointError, ConfigError

if TYPE_CHECKING:
    import torch

FORMAT = "pcc_ros.checkpoint/1"
_REQUIRED_KEYS = ("format", "backend", "hyper_parameters", "tensors", "sha256")
#: Every top-level key :func:`make_config` / :func:`save_checkpoint` / ``pcc train`` write.
_KNOWN_KEYS = frozenset({
    *_REQUIRED_KEYS, "points", "training", "metrics", "git_revision", "pcc_ros_version", "created", "dtypes",
    "size_bytes", "resume", "box_aspect",
})
#: Deepest JSON nesting a checkpoint config may have (real ones are about 4 levels deep).
MAX_CONFIG_DEPTH = 32


def parse_box_aspect(value: Any) -> tuple[float, float]:
    """``(width / length, height / length)`` from a pair or a checkpoint's ``box_aspect`` record."""
    if isinstance(value, dict):
        value = (value.get("width_over_length"), value.get("height_over_length"))
    try:
        pair = tuple(float(v) for v in value)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"box_aspect must be (width/length, height/length), got {value!r}") from exc
    if len(pair) != 2 or not all(np.isfinite(pair)) or not all(0.05 < v < 5.0 for v in pair):
        raise ConfigError(f"box_aspect must be two ratios in (0.05, 5), got {value!r}")
    return pair  # type: ignore[return-value]


def box_aspect_record(aspect: Sequence[float], source: str = "") -> dict[str, Any]:
    """The checkpoint JSON entry ``box_aspect`` (read back by :func:`parse_box_aspect`)."""
    w, h = parse_box_aspect(aspect)
    record: dict[str, Any] = {"width_over_length": round(w, 6), "height_over_length": round(h, 6)}
    if source:
        record["source"] = source
    return record


def checkpoint_paths(path: str | Path) -> tuple[Path, Path]:
    """``(weights, config)`` for ``NAME``, ``NAME.safetensors`` or ``NAME.json``."""
    path = Path(path)
    if path.suffix in (".safetensors", ".json"):
        stem = path.with_suffix("")
    else:
        stem = path
    return stem.with_name(stem.name + ".safetensors"), stem.with_name(stem.name + ".json")


def git_revision(start: str | Path | None = None) -> str:
    """The repository's HEAD commit (``+dirty`` if modified), or ``"unknown"`` outside git."""
    cwd = Path(start) if start else Path(__file__).resolve().parent
    try:
        rev = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=cwd, capture_output=True, text=True, timeout=5, check=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            cwd=cwd, capture_output=True, text=True, timeout=5, check=True,
        ).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return rev + ("+dirty" if dirty else "")


def make_config(
    backend: str,
    hyper_parameters: Mapping[str, Any],
    *,
    training: Mapping[str, Any] | None = None,
    metrics: Mapping[str, Any] | None = None,
    extra: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """A checkpoint config (without the tensor manifest, which :func:`save_checkpoint` adds).

    Point counts are pulled out of the hyper-parameters (keys containing ``points``) into
    ``"points"`` so a person reading the JSON sees them at a glance.
    """
    hyper = json.loads(json.dumps(dict(hyper_parameters)))  # JSON-able, detached copy
    config: dict[str, Any] = {
        "format": FORMAT,
        "backend": backend,
        "hyper_parameters": hyper,
        "points": {k: v for k, v in hyper.items() if "points" in k},
        "training": dict(training or {}),
        "metrics": dict(metrics or {}),
        "git_revision": git_revision(),
        "pcc_ros_version": __version__,
        "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
    }
    if extra:
        unknown = sorted(set(extra) - _KNOWN_KEYS)
        if unknown:  # readers refuse unknown keys: a new one must be registered in _KNOWN_KEYS
            raise ValueError(f"checkpoint config keys {unknown} are not in checkpoint._KNOWN_KEYS")
        config.update(extra)
    return config


def sha256_file(path: Path) -> str:
    digest = hashlib.sha256()
    with path.open("rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def save_checkpoint(path: str | Path, model_state: Mapping[str, torch.Tensor], config: Mapping[str, Any]) -> Path:
    """Write weights and config atomically (temp files + rename); returns the weights path.

    ``config`` needs at least ``backend`` and ``hyper_parameters`` (see :func:`make_config`);
    ``format``, the tensor manifest and the hash are filled in here.
    """
    import torch
    from safetensors.torch import save

    weights_path, config_path = checkpoint_paths(path)
    if "backend" not in config or "hyper_parameters" not in config:
        raise ValueError("checkpoint config needs 'backend' and 'hyper_parameters'")
    tensors = {}
    for name, value in model_state.items():
        if not isinstance(value, torch.Tensor):
            raise TypeError(f"state entry {name!r} is {type(value).__name__}, not a tensor")
        tensors[name] = value.detach().to("cpu").contiguous().clone()  # clone: no shared storage
    full = dict(config)
    full["format"] = FORMAT
    full["tensors"] = {name: list(t.shape) for name, t in tensors.items()}
    full["dtypes"] = {name: str(t.dtype).removeprefix("torch.") for name, t in tensors.items()}

    weights_path.parent.mkdir(parents=True, exist_ok=True)
    blob = save(tensors, metadata={"format": FORMAT, "backend": str(config["backend"])})
    full["sha256"] = hashlib.sha256(blob).hexdigest()
    full["size_bytes"] = len(blob)
    # weights first: a config is only ever next to the weights it describes
    files.write_bytes(weights_path, blob)
    files.write_json(config_path, full, indent=2, sort_keys=False)
    return weights_path


def load_config(path: str | Path) -> dict[str, Any]:
    """The validated JSON config of a checkpoint (no tensors are read)."""
    _, config_path = checkpoint_paths(path)
    if not config_path.is_file():
        raise CheckpointError(f"{config_path}: checkpoint config not found")
    try:
        config = json.loads(config_path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CheckpointError(f"{config_path}: not a valid JSON checkpoint config ({exc})") from exc
    except RecursionError:
        raise CheckpointError(f"{config_path}: JSON nested too deeply to parse (limit {MAX_CONFIG_DEPTH} levels)",
                              hint="the file is not a checkpoint config; re-copy or re-train it") from None
    if not isinstance(config, dict):
        raise CheckpointError(f"{config_path}: checkpoint config must be a JSON object")
    depth = _depth(config)
    if depth > MAX_CONFIG_DEPTH:
        raise CheckpointError(f"{config_path}: JSON nested more than {MAX_CONFIG_DEPTH} levels deep",
                              hint="the file is not a checkpoint config; re-copy or re-train it")
    missing = [k for k in _REQUIRED_KEYS if k not in config]
    if missing:
        raise CheckpointError(f"{config_path}: checkpoint config lacks {missing}")
    unknown = sorted(set(config) - _KNOWN_KEYS)
    if unknown:
        raise CheckpointError(f"{config_path}: unknown checkpoint config keys {unknown[:5]}",
                              hint=f"a {FORMAT} config has only {sorted(_KNOWN_KEYS)}; was the file edited?")
    if config["format"] != FORMAT:
        raise CheckpointError(f"{config_path}: unsupported checkpoint format {config['format']!r} (expected {FORMAT})")
    if not isinstance(config["tensors"], dict) or not isinstance(config["hyper_parameters"], dict):
        raise CheckpointError(f"{config_path}: 'tensors' and 'hyper_parameters' must be JSON objects")
    return config


def set_box_aspect(path: str | Path, aspect: Any, source: str) -> Path:
    """Record the reference box aspect (``Completer.box_aspect``) in an existing checkpoint's
    JSON, e.g. the median aspect of the data weights were trained on; ``source`` says where it
    comes from. The weights are untouched. Returns the JSON path."""
    _, config_path = checkpoint_paths(path)
    config = load_config(path)
    config["box_aspect"] = box_aspect_record(aspect, source)
    lines = config_path.read_text().splitlines()
    indent = len(lines[1]) - len(lines[1].lstrip(" ")) if len(lines) > 1 else 2  # keep the file's own layout
    files.write_json(config_path, config, indent=max(indent, 1), sort_keys=False)
    return config_path


def load_checkpoint(path: str | Path, verify_hash: bool = True) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """``(state_dict, config)`` of a checkpoint, fully validated, on the CPU.

    Raises:
        CheckpointError: a file is missing, the JSON is malformed, the weights are truncated
            or corrupt (header parse failure or SHA-256 mismatch), the tensors differ from
            the config's manifest, or a tensor holds NaN/inf.
    """
    import torch
    from safetensors.torch import load_file

    weights_path, config_path = checkpoint_paths(path)
    if not weights_path.is_file():
        raise CheckpointError(f"{weights_path}: checkpoint weights not found")
    config = load_config(path)
    size = weights_path.stat().st_size
    recorded = config.get("size_bytes")
    if isinstance(recorded, int) and size != recorded:
        raise CheckpointError(
            f"{weights_path}: weights file is {size} bytes but {config_path.name} records {recorded} "
            f"({'truncated' if size < recorded else 'trailing data'}; re-copy or re-train the checkpoint)"
        )
    if verify_hash:
        actual = sha256_file(weights_path)
        if actual != config["sha256"]:
            raise CheckpointError(
                f"{weights_path}: weights are corrupt or were replaced (sha256 {actual[:12]}… differs from "
                f"{str(config['sha256'])[:12]}… recorded in {config_path.name})"
            )
    try:
        state = load_file(str(weights_path), device="cpu")
    except (SafetensorError, OSError, ValueError, RuntimeError) as exc:
        raise CheckpointError(f"{weights_path}: cannot read safetensors weights (truncated or corrupt): {exc}") from exc
    try:
        expected = {str(name): tuple(int(d) for d in shape) for name, shape in dict(config["tensors"]).items()}
    except (TypeError, ValueError) as exc:
        raise CheckpointError(f"{config_path}: malformed tensor manifest ({exc})") from exc
    actual_shapes = {name: tuple(t.shape) for name, t in state.items()}
    problems = _compare_shapes(expected, actual_shapes, "config", "file")
    if problems:
        raise CheckpointError(f"{weights_path}: weights do not match {config_path.name}: {problems}")
    recorded_dtypes = config.get("dtypes")
    if recorded_dtypes is not None:
        if not isinstance(recorded_dtypes, dict):
            raise CheckpointError(f"{config_path}: 'dtypes' must be a JSON object")
        wrong = [f"{n}: config {recorded_dtypes.get(n)} vs file {str(t.dtype).removeprefix('torch.')}"
                 for n, t in state.items() if str(recorded_dtypes.get(n)) != str(t.dtype).removeprefix("torch.")]
        if wrong:
            raise CheckpointError(f"{weights_path}: tensor dtypes do not match {config_path.name}: {wrong[:3]}"
                                  + (" …" if len(wrong) > 3 else ""), hint="re-export or re-train the checkpoint")
    for name, tensor in state.items():
        if tensor.is_floating_point() and not bool(torch.isfinite(tensor).all()):
            raise CheckpointError(f"{weights_path}: tensor {name!r} holds NaN or inf values")
    return state, config


def check_hyper_parameters(config: Mapping[str, Any], defaults: Mapping[str, Any], source: str) -> dict[str, Any]:
    """The checkpoint's hyper-parameters, refused unless they name exactly the backend's
    (``defaults``): an unknown one would be ignored, a missing one silently defaulted."""
    hyper = dict(config.get("hyper_parameters", {}))
    backend = config.get("backend")
    unknown = sorted(set(hyper) - set(defaults))
    if unknown:
        raise CheckpointError(f"{source}: config has hyper-parameters {unknown} unknown to backend {backend!r}")
    missing = sorted(set(defaults) - set(hyper))
    if missing:
        raise CheckpointError(
            f"{source}: config lacks hyper-parameters {missing} of backend {backend!r}",
            hint="the weights were built with values nobody recorded; re-train, or add them to the JSON "
            "if you know them",
        )
    return hyper


def _depth(value: Any) -> int:
    """Nesting depth of a parsed JSON value (iterative, so any depth is measured safely)."""
    deepest, stack = 0, [(value, 1)]
    while stack:
        item, level = stack.pop()
        deepest = max(deepest, level)
        if deepest > MAX_CONFIG_DEPTH:
            return deepest
        children = item.values() if isinstance(item, dict) else item if isinstance(item, list) else ()
        stack.extend((child, level + 1) for child in children if isinstance(child, (dict, list)))
    return deepest


def _compare_shapes(expected: Mapping[str, tuple], actual: Mapping[str, tuple], a: str, b: str, limit: int = 5) -> str:
    missing = sorted(set(expected) - set(actual))
    unexpected = sorted(set(actual) - set(expected))
    wrong = sorted(n for n in set(expected) & set(actual) if tuple(expected[n]) != tuple(actual[n]))
    parts = []
    if missing:
        parts.append(f"missing in {b}: {missing[:limit]}" + (" …" if len(missing) > limit else ""))
    if unexpected:
        parts.append(f"not in {a}: {unexpected[:limit]}" + (" …" if len(unexpected) > limit else ""))
    for n in wrong[:limit]:
        parts.append(f"{n}: {a} {list(expected[n])} vs {b} {list(actual[n])}")
    return "; ".join(parts)


def validate_state(model: torch.nn.Module, state: Mapping[str, torch.Tensor], source: str = "checkpoint") -> None:
    """Raise :class:`CheckpointError` unless ``state`` has exactly the model's names and shapes,
    and dtypes that load without a silent cast (float32 weights load into any float model)."""
    import torch

    expected = {name: tuple(t.shape) for name, t in model.state_dict().items()}
    actual = {name: tuple(t.shape) for name, t in state.items()}
    problems = _compare_shapes(expected, actual, "model", "checkpoint")
    if problems:
        raise CheckpointError(f"{source}: weights do not fit the model built from its config: {problems}")
    model_state = model.state_dict()
    wrong = [f"{n}: model {str(model_state[n].dtype).removeprefix('torch.')} vs checkpoint "
             f"{str(t.dtype).removeprefix('torch.')}" for n, t in state.items()
             if t.dtype != model_state[n].dtype and not (t.is_floating_point() and model_state[n].is_floating_point()
                                                        and t.dtype == torch.float32)]
    if wrong:  # a float16 / int32 tensor would be cast silently by load_state_dict
        raise CheckpointError(f"{source}: tensor dtypes do not fit the model: {wrong[:3]}"
                              + (" …" if len(wrong) > 3 else ""), hint="the weights must be saved in float32")
