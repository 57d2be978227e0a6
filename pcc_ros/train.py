"""Train a completion backend self-supervised from partial scans (``pcc train BACKEND``).

The loop is generic. A trainable backend's class (``get_backend(BACKEND)``) owns its recipe:
``cls.training_recipe(size, **options)`` returns an object with

* ``build_completer(device) -> TorchCompleter`` (the network is its ``.model``),
* ``training_data(cache, split, min_points)`` -> the backend's own training set, built
  from an instance cache (partial observations only),
* ``batches(data, batch_size, config, rng)`` -> endless iterator of batches with ``.to(device)``,
* ``loss(net, batch) -> (loss tensor, {name: float})``,
* ``describe() -> dict`` (stored in the checkpoint), and ``default_lr`` (optional).

A recipe lives beside its network in ``models/``, which never imports ``data/`` or this module;
one that reads caches declares a ``kit`` attribute, and :func:`load_recipe` sets it to
:func:`training_kit` (``models.base.TrainingKit``: the cache loader, TraPCC's ground-truth
pools, :func:`validation_instances` and :func:`validate`).

This module owns everything else: seeds, devices, DistributedDataParallel under
``torchrun`` (``WORLD_SIZE`` / ``LOCAL_RANK``), the learning-rate schedule, tqdm, periodic
validation with the evaluation metrics on a held-out split, resumable checkpoints and a
PNG of the training curves.

Output directory::

    OUT/<backend>.safetensors + .json   the trained weights (common checkpoint format;
                                        pass to --checkpoint / load_completer)
    OUT/resume.safetensors + .json      weights + optimizer state + step (for --resume)
    OUT/log.jsonl                       one line per logging interval / validation
    OUT/training.png                    loss and validation curves

Ground-truth shapes (SynthCars) are read only by the validation metrics, through the
evaluation module; training batches come from the instance cache, which holds none.

``train(TrainConfig(...))`` is the library; ``pcc train`` (:mod:`pcc_ros.cli.train`) builds the
:class:`TrainConfig` from its flags. Example::

    pcc train pointpncnet --data cache/ --out runs/pnc --iterations 4000 --batch-size 32
    torchrun --nproc-per-node 4 -m pcc_ros.cli train pointpncnet --data cache/ --out runs/pnc --device cuda
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import os
import platform
import time
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from pcc_ros.assignments import parse_assignments
from pcc_ros.data import gt_pools
from pcc_ros.data.instance_cache import InstanceCache
from pcc_ros.errors import CheckpointError, ConfigError, TrainingError
from pcc_ros.evaluate import instances_from_cache, score_backend
from pcc_ros.models.base import TrainingKit, select_device
from pcc_ros.models.checkpoint import load_checkpoint, make_config, save_checkpoint, validate_state
from pcc_ros.models.registry import get_backend

log = logging.getLogger("pcc.train")

RESUME_NAME = "resume"
_OPT_PREFIX = "optimizer."
_MODEL_PREFIX = "model."


@dataclass
class TrainConfig:
    """Everything a training run is told; ``pcc train`` builds it from its flags (same names)."""

    backend: str
    data: Path
    out: Path
    size: str = "default"  # the backend's preset (--config)
    iterations: int = 4000
    batch_size: int = 32
    lr: float | None = None  # None: the recipe's default_lr (5e-4)
    lr_decay_every: int | None = None  # None: a quarter of the iterations
    seed: int = 0
    resume: bool = False
    inpainting: bool = True
    stage: str | None = None
    options: dict[str, Any] = field(default_factory=dict)  # backend training options (parsed --option)
    device: str = "auto"
    split: str = "train"
    val_split: str = "val"
    val_instances: int = 200
    val_every: int = 500
    checkpoint_every: int = 250
    min_points: int = 10
    threads: int | None = None
    progress: bool = True
    real_data: list[Path] = field(default_factory=list)
    real_share: float = 0.1
    init: Path | None = None
    select_by: str = "cd_l1"


# --------------------------------------------------------------------------- helpers


def parse_options(items: list[str]) -> dict[str, Any]:
    """``KEY=VALUE`` strings to a dict; values parsed as JSON (``2``, ``0.3``, ``true``) else strings."""
    options: dict[str, Any] = {}
    for key, value in parse_assignments(items, "--option", "KEY=VALUE", require_value=False).items():
        try:
            options[key] = json.loads(value)
        except json.JSONDecodeError:
            options[key] = value
    return options


def load_recipe(backend: str, size: str, options: dict[str, Any]) -> Any:
    """The backend's training recipe (``cls.training_recipe``); :class:`ConfigError` if it has none or
    the options are wrong."""
    cls = get_backend(backend)  # ConfigError for unknown names
    try:
        recipe = cls.training_recipe(size=size, **options)  # the base class refuses backends without weights
    except (TypeError, ValueError) as exc:  # an unknown key, or a value a recipe cannot convert
        raise ConfigError(f"backend {backend!r}: invalid training options {sorted(options)}: {exc}") from exc
    check_option_types(getattr(recipe, "options", None), backend)
    if hasattr(recipe, "kit"):  # a recipe that reads caches gets them (and validation) from here
        recipe.kit = training_kit()
    return recipe


def _accepts(kind: Any, value: Any) -> bool | None:
    """Whether ``value`` fits the annotation ``kind`` (None: a kind this check does not know)."""
    if kind is type(None):
        return value is None
    if kind is bool:
        return isinstance(value, bool)
    if kind is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if kind is float:  # JSON writes 1.0 as 1: an integer is a float option's value too
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if kind is str:
        return isinstance(value, str)
    if typing.get_origin(kind) in (list, tuple):
        return isinstance(value, (list, tuple))
    return None


def check_option_types(options: Any, backend: str) -> None:
    """Every field of a recipe's options dataclass against its annotation, so ``--option views=abc``
    is refused naming the option and the type it needs, not a TypeError deep in training."""
    if not dataclasses.is_dataclass(options):
        return
    hints = typing.get_type_hints(type(options))
    for item in dataclasses.fields(options):
        kind = hints.get(item.name)
        kinds = typing.get_args(kind) if isinstance(kind, types.UnionType) or typing.get_origin(kind) is typing.Union \
            else (kind,)
        verdicts = [_accepts(k, getattr(options, item.name)) for k in kinds]
        if None in verdicts or any(verdicts):
            continue
        names = " or ".join("null" if k is type(None) else getattr(k, "__name__", str(k)) for k in kinds)
        raise ConfigError(f"backend {backend!r}: --option {item.name}={json.dumps(getattr(options, item.name))} "
                          f"must be {names}")


def training_kit() -> TrainingKit:
    """What the recipes of ``models/`` use from ``data/`` and this module (they never import them)."""
    return TrainingKit(open_cache=InstanceCache.load, validation_instances=validation_instances, validate=validate,
                       pool_config=gt_pools.PoolConfig, load_or_build_pools=gt_pools.load_or_build_pools,
                       load_or_assign=gt_pools.load_or_assign)


def learning_rate(base: float, step: int, every: int) -> float:
    """Step decay: ``base * 0.5 ** (step // every)`` (PointPnCNet: halved every quarter of training)."""
    return base * 0.5 ** (step // max(1, every))


@dataclass
class Distributed:
    """Process-group facts; ``world == 1`` outside torchrun."""

    rank: int = 0
    local_rank: int = 0
    world: int = 1

    @property
    def main(self) -> bool:
        return self.rank == 0

    @classmethod
    def from_env(cls) -> Distributed:
        world = int(os.environ.get("WORLD_SIZE", "1"))
        if world <= 1:
            return cls()
        return cls(int(os.environ.get("RANK", "0")), int(os.environ.get("LOCAL_RANK", "0")), world)


def optimizer_tensors(optimizer: Any) -> tuple[dict[str, Any], dict[str, Any]]:
    """Flatten an optimizer state dict into named tensors + a JSON-able remainder (no pickle)."""
    import torch

    state = optimizer.state_dict()
    tensors: dict[str, torch.Tensor] = {}
    scalars: dict[str, dict[str, Any]] = {}
    for pid, entry in state["state"].items():
        for key, value in entry.items():
            if isinstance(value, torch.Tensor):
                tensors[f"{_OPT_PREFIX}{pid}.{key}"] = value
            else:
                scalars.setdefault(str(pid), {})[key] = value
    return tensors, {"param_groups": state["param_groups"], "scalars": scalars}


def restore_optimizer(optimizer: Any, tensors: dict[str, Any], meta: dict[str, Any], source: Path) -> None:
    state: dict[int, dict[str, Any]] = {}
    for name, value in tensors.items():
        pid, _, key = name[len(_OPT_PREFIX):].partition(".")
        state.setdefault(int(pid), {})[key] = value
    for pid, entry in meta.get("scalars", {}).items():
        state.setdefault(int(pid), {}).update(entry)
    # JSON turned tuples (Adam's betas) into lists: restore them so the state is identical.
    groups = [{k: (tuple(v) if isinstance(v, list) and k != "params" else v) for k, v in g.items()}
              for g in meta["param_groups"]]
    try:
        optimizer.load_state_dict({"state": state, "param_groups": groups})
    except (KeyError, ValueError, RuntimeError) as exc:
        raise CheckpointError(f"{source}: optimizer state does not fit this model: {exc}") from exc


def save_resume(out: Path, backend: str, completer: Any, optimizer: Any, step: int, run: dict[str, Any]) -> Path:
    """Weights + optimizer state (safetensors) and step + run settings (JSON) for ``--resume``."""
    opt_tensors, opt_meta = optimizer_tensors(optimizer)
    tensors = {_MODEL_PREFIX + k: v for k, v in completer.model.state_dict().items()}
    tensors.update(opt_tensors)
    config = make_config(backend, completer.config, extra={"resume": {"step": step, "optimizer": opt_meta, **run}})
    return save_checkpoint(out / f"{RESUME_NAME}.safetensors", tensors, config)


def load_resume(out: Path, backend: str, completer: Any, optimizer: Any) -> tuple[int, dict[str, Any]]:
    """Restore weights and optimizer from ``OUT/resume``; returns ``(step, run settings)``."""
    path = out / f"{RESUME_NAME}.safetensors"
    state, config = load_checkpoint(path)
    if config["backend"] != backend:
        raise CheckpointError(f"{path}: resume checkpoint is for {config['backend']!r}, not {backend!r}")
    if config["hyper_parameters"] != completer.config:
        raise CheckpointError(f"{path}: resume checkpoint was made with another model config (--config / options)")
    resume = config.get("resume")
    if not isinstance(resume, dict) or "step" not in resume:
        raise CheckpointError(f"{path}: not a resume checkpoint (no 'resume' section)")
    model_state = {k[len(_MODEL_PREFIX):]: v for k, v in state.items() if k.startswith(_MODEL_PREFIX)}
    validate_state(completer.model, model_state, source=str(path))
    completer.model.load_state_dict(model_state, strict=True)
    restore_optimizer(optimizer, {k: v for k, v in state.items() if k.startswith(_OPT_PREFIX)},
                       resume["optimizer"], path)
    return int(resume["step"]), resume


# --------------------------------------------------------------------------- validation


def validate(completer: Any, instances: list[Any], seed: int) -> dict[str, float]:
    """Mean evaluation metrics (canonical units, no EMD) of ``completer`` on ``instances``."""
    if not instances:
        return {}
    was_training = completer.model.training
    try:
        _, rows, seconds = score_backend(completer, instances, seed=seed, with_emd=False, progress=False)
    finally:
        completer.model.train(was_training)
    keys = ("cd_l1", "precision", "coverage", "fscore")
    out = {f"val_{k}": float(np.nanmean([r[k] for r in rows])) for k in keys if k in rows[0]}
    out["val_instances"] = len(instances)
    out["val_seconds"] = round(seconds, 3)
    return out


def validation_instances(cache: Any, split: str, count: int, seed: int) -> tuple[list[Any], str]:
    """A seeded subset of the validation split with its reference (ground truth or aggregate)."""
    if count <= 0 or len(cache.indices(split)) == 0:
        return [], "none"
    return instances_from_cache(cache, split, count, seed)


# --------------------------------------------------------------------------- plotting


def init_weights(completer: Any, path: Path) -> dict[str, Any]:
    """Load a checkpoint's weights into ``completer`` (same backend and size); what was loaded."""
    state, config = load_checkpoint(path)
    if config.get("backend") != completer.name:
        raise CheckpointError(f"{path}: a {config.get('backend')!r} checkpoint cannot initialise {completer.name!r}")
    validate_state(completer.model, state, source=str(path))
    completer.model.load_state_dict(state)
    return {"path": str(path), "sha256": config.get("sha256"), "metrics": config.get("metrics", {}),
            "training_steps": config.get("training", {}).get("steps")}


def machine_info() -> dict[str, Any]:
    """Where a run trained: host, CPU, threads, load (recorded in the checkpoint)."""
    import torch

    info: dict[str, Any] = {"host": platform.node(), "platform": platform.platform(),
                            "processor": platform.processor() or platform.machine(), "cpu_count": os.cpu_count(),
                            "torch_threads": torch.get_num_threads(), "torch": torch.__version__,
                            "cuda": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None}
    with contextlib.suppress(OSError):
        info["load_average"] = [round(x, 2) for x in os.getloadavg()]
    return info


def mix_real(
    recipe: Any, data: list[Any], real_caches: list[Path], share: float, min_points: int
) -> tuple[list[Any], dict[str, Any]]:
    """Mix the training groups of real-scan caches into ``data`` at ``share`` of all groups.

    Real scans are few, so their groups are repeated (references, no copies) until they make
    up ``share`` of an epoch; what was mixed is returned for the checkpoint config.
    """
    if not real_caches:
        return data, {"caches": [], "share": 0.0}
    if not 0.0 < share < 1.0:
        raise ConfigError(f"--real-share must be in (0, 1), got {share}")
    real: list[Any] = []
    per_cache = {}
    for path in real_caches:
        groups = recipe.training_data(InstanceCache.load(path), None, min_points=min_points)
        per_cache[str(path)] = {"groups": len(groups), "observations": sum(len(g) for g in groups)}
        real.extend(groups)
    if not real:
        raise ConfigError(f"--real-data {', '.join(map(str, real_caches))}: no usable real observations")
    repeats = max(1, int(np.ceil(share * len(data) / ((1.0 - share) * len(real)))))
    mixed = [*data, *(real * repeats)]
    effective = len(real) * repeats / len(mixed)
    log.info("real scans: %d groups x %d repeats = %.1f %% of the training groups", len(real), repeats,
             100 * effective)
    return mixed, {"caches": per_cache, "groups": len(real), "repeats": repeats, "share_requested": share,
                   "share": round(effective, 4)}


def plot_log(records: list[dict[str, Any]], path: Path, title: str, best: dict[str, Any] | None = None,
             select_key: str = "val_cd_l1") -> None:
    """Training loss (and its parts) and validation Chamfer-L1 against the step, as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    train = [r for r in records if "loss" in r]
    val = [r for r in records if any(k.startswith("val_") and k not in ("val_instances", "val_seconds") for k in r)]
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for key in sorted({k for r in train for k in r if k not in ("step", "lr", "seconds", "instances_per_s")}):
        axes[0].plot([r["step"] for r in train], [r[key] for r in train], label=key)
    axes[0].set(xlabel="step", ylabel="loss (canonical units)", title="training loss")
    if train:
        axes[0].legend()
    for key in ("val_cd_l1", "val_precision", "val_coverage", "val_loss", "val_iou", "val_sdf_iou"):
        if val and key in val[0]:
            axes[1].plot([r["step"] for r in val], [r[key] for r in val], marker="o", label=key[4:])
    if val and "val_fscore" in val[0]:
        twin = axes[1].twinx()
        twin.plot([r["step"] for r in val], [r["val_fscore"] for r in val], marker="s", color="tab:red",
                  label="F-score@1% (right axis)")
        twin.set_ylabel("F-score@1%")
        twin.legend(loc="upper center", fontsize=8)
    if best is not None and select_key in best:
        axes[1].axvline(best["step"], color="0.5", ls="--", lw=1)
        axes[1].annotate(f"selected: step {best['step']}\n{select_key[4:]} {best[select_key]:.4f}",
                         (best["step"], best[select_key]), fontsize=8, xytext=(5, 12), textcoords="offset points")
    axes[1].set(xlabel="step", ylabel="canonical units", title="validation (held-out split)")
    if val:
        axes[1].legend()
    fig.suptitle(title)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)


# --------------------------------------------------------------------------- the loop


def train(opts: TrainConfig) -> dict[str, Any]:
    """Run training as ``opts`` says; returns the final summary (also in the checkpoint)."""
    import torch

    if opts.iterations < 1 or opts.batch_size < 1:
        raise ConfigError("--iterations and --batch-size must be >= 1")
    dist = Distributed.from_env()
    if opts.threads:
        torch.set_num_threads(opts.threads)
    options = dict(opts.options)
    if not opts.inpainting:
        options["inpainting"] = False
    if opts.stage:
        options["stage"] = opts.stage
    recipe = load_recipe(opts.backend, opts.size, options)

    if dist.world > 1:
        backend = "nccl" if torch.cuda.is_available() and opts.device != "cpu" else "gloo"
        torch.distributed.init_process_group(backend=backend)
        device = f"cuda:{dist.local_rank}" if backend == "nccl" else "cpu"
        if backend == "nccl":
            torch.cuda.set_device(dist.local_rank)
    else:
        device = str(select_device(opts.device))

    torch.manual_seed(opts.seed)  # same initial weights on every rank
    completer = recipe.build_completer(device)
    init = None
    if opts.init is not None and not opts.resume:
        init = init_weights(completer, opts.init)
    net = completer.model
    net.train()
    lr = opts.lr if opts.lr is not None else float(getattr(recipe, "default_lr", 5e-4))
    decay_every = opts.lr_decay_every or max(1, opts.iterations // 4)
    optimizer = torch.optim.Adam(net.parameters(), lr=lr)

    out: Path = opts.out
    out.mkdir(parents=True, exist_ok=True)
    run_settings = {
        "backend": opts.backend, "config": opts.size, "iterations": opts.iterations,
        "batch_size": opts.batch_size, "world_size": dist.world, "lr": lr, "lr_decay_every": decay_every,
        "seed": opts.seed, "data": str(opts.data), "split": opts.split, "recipe": recipe.describe(),
    }
    if init is not None:
        run_settings["init"] = init
    step = 0
    log_path = out / "log.jsonl"
    if opts.resume:
        step, previous = load_resume(out, opts.backend, completer, optimizer)
        if opts.lr_decay_every is None and "lr_decay_every" in previous:
            # a longer --iterations must not move the decay steps of the run being continued
            decay_every = int(previous["lr_decay_every"])
            run_settings["lr_decay_every"] = decay_every
        changed = {k: (previous.get(k), v) for k, v in run_settings.items()
                   if k not in ("iterations", "data") and previous.get(k) != v}
        if changed:
            raise ConfigError(f"--resume with different settings than the saved run: {changed}")
        log.info("resumed %s at step %d", out / f"{RESUME_NAME}.safetensors", step)
    elif (out / f"{RESUME_NAME}.json").exists():
        raise ConfigError(f"{out} already holds a training run; pass --resume to continue or use another --out")
    elif dist.main:
        log_path.unlink(missing_ok=True)

    # Optional recipe hooks (a backend whose data is not an instance cache, its own validation,
    # a step between loading and training, a last transformation of saved weights):
    # open_data, validation_data, validate, prepare, finalize, summary, select_metric.
    cache = getattr(recipe, "open_data", InstanceCache.load)(opts.data)
    if hasattr(cache, "check_finite"):
        cache.check_finite()
    t0 = time.perf_counter()
    own_mixing = hasattr(recipe, "use_real_data")  # TraPCC mixes real caches itself (into its GT pools too)
    if own_mixing and opts.real_data:
        recipe.use_real_data([str(p) for p in opts.real_data], opts.real_share)
    data = recipe.training_data(cache, opts.split, min_points=opts.min_points)
    total_views = sum(len(g) for g in data) if isinstance(data, list) else len(data)
    log.info("training data: %d groups, %d observations of split %r (%.1f s)",
             len(data), total_views, opts.split, time.perf_counter() - t0)
    if own_mixing:
        mixing = recipe.data_summary()
    else:
        if opts.real_data and not isinstance(data, list):
            raise ConfigError(f"backend {opts.backend!r} takes real-scan caches through its own option, "
                              "not --real-data")
        data, mixing = mix_real(recipe, data, opts.real_data, opts.real_share, opts.min_points)
    run_settings["real_data"] = mixing
    val_instances, reference = ([], "none")
    if dist.main:
        find_val = getattr(recipe, "validation_data", validation_instances)
        val_instances, reference = find_val(cache, opts.val_split, opts.val_instances, opts.seed)
        log.info("validation: %d instances of split %r against %s", len(val_instances), opts.val_split, reference)
    validate_fn = getattr(recipe, "validate", validate)
    if hasattr(recipe, "prepare"):
        recipe.prepare(completer, data, val_instances, opts.seed)

    train_net: Any = net
    if dist.world > 1:
        from torch.nn.parallel import DistributedDataParallel

        train_net = DistributedDataParallel(net, device_ids=[dist.local_rank] if device.startswith("cuda") else None)

    # Batch sampling is a pure function of (seed, rank, start step): a resumed run is reproducible.
    rng = np.random.default_rng([opts.seed, dist.rank, step])
    batches = recipe.batches(data, opts.batch_size, completer.config, rng)
    records: list[dict[str, Any]] = []
    if log_path.exists():
        records = [json.loads(line) for line in log_path.read_text().splitlines() if line.strip()]

    def emit(record: dict[str, Any]) -> None:
        if not dist.main:
            return
        records.append(record)
        with log_path.open("a") as f:
            f.write(json.dumps(record) + "\n")

    select_key = getattr(recipe, "select_metric", None) or f"val_{opts.select_by}"
    lower_better = select_key != "val_fscore"

    def best_record() -> dict[str, Any] | None:
        vals = [r for r in records if select_key in r and np.isfinite(r[select_key]) and r["step"] > 0]
        if not vals:
            return None
        return (min if lower_better else max)(vals, key=lambda r: r[select_key])

    def save_weights(name: str, record: dict[str, Any]) -> None:
        training = {
            **run_settings, "steps": step, "groups": len(data), "observations": total_views,
            "validation_reference": reference, "wall_seconds": round(time.perf_counter() - started, 1),
            "device": str(device), "machine": machine_info(), "selected_by": select_key,
            "selected_step": record.get("step", step),
        }
        if hasattr(recipe, "data_summary"):  # what the backend trained on (e.g. TraPCC's real-data share)
            training["data_summary"] = recipe.data_summary()
        current = None
        if hasattr(recipe, "finalize"):  # a last transformation of the saved weights only (AML's whitening)
            current = {k: v.clone() for k, v in completer.model.state_dict().items()}
            recipe.finalize(completer, data)
        training.update(recipe.summary() if hasattr(recipe, "summary") else {})
        completer.save(out / f"{name}.safetensors", training=training,
                       metrics={k: v for k, v in record.items() if k.startswith("val_")})
        if current is not None:
            completer.model.load_state_dict(current)

    def on_validation(record: dict[str, Any]) -> None:
        """Keep the best weights by validation (the shipped checkpoint is the best, not the last)."""
        if dist.main and best_record() is record:
            save_weights(opts.backend, record)
            log.info("step %d: best %s so far (%.5f): wrote %s", step, select_key, record[select_key],
                     out / f"{opts.backend}.safetensors")

    def checkpoint(final: bool = False) -> None:
        if not dist.main:
            return
        save_resume(out, opts.backend, completer, optimizer, step, run_settings)
        if final:
            last_val = next((r for r in reversed(records) if select_key in r), {})
            save_weights(f"{opts.backend}_last", last_val)
            if best_record() is None:  # no validation data: the last weights are all there is
                save_weights(opts.backend, last_val)
        plot_log(records, out / "training.png", f"pcc train {opts.backend} ({opts.size})",
                 best=best_record(), select_key=select_key)

    started = time.perf_counter()
    if dist.main and init is not None and step == 0 and val_instances:
        emit({"step": 0, **validate_fn(completer, val_instances, opts.seed)})  # where the initial weights stand
        log.info("initial weights %s: %s", opts.init, records[-1])
    window: dict[str, list[float]] = {}
    window_start = time.perf_counter()
    log_every = 50
    bar = tqdm(total=opts.iterations, initial=step, desc=f"train {opts.backend}", unit="step",
               disable=not opts.progress or not dist.main)
    try:
        while step < opts.iterations:
            current_lr = learning_rate(lr, step, decay_every)
            for group in optimizer.param_groups:
                group["lr"] = current_lr
            batch = next(batches).to(completer.device)
            loss, stats = recipe.loss(train_net, batch)
            if not torch.isfinite(loss):
                raise TrainingError(f"{opts.data}: non-finite training loss at step {step} ({stats})",
                                    hint="the run diverged: lower --lr or resume from the last checkpoint")
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            step += 1
            for k, v in stats.items():
                window.setdefault(k, []).append(v)
            bar.update(1)
            bar.set_postfix(loss=f"{stats['loss']:.4f}")
            if step % log_every == 0 or step == opts.iterations:
                seconds = time.perf_counter() - window_start
                n = len(next(iter(window.values())))
                emit({"step": step, "lr": current_lr, **{k: float(np.mean(v)) for k, v in window.items()},
                      "instances_per_s": round(n * opts.batch_size * dist.world / max(seconds, 1e-9), 1)})
                window, window_start = {}, time.perf_counter()
            if dist.main and opts.val_every and step % opts.val_every == 0 and step < opts.iterations:
                emit({"step": step, **validate_fn(completer, val_instances, opts.seed)})
                log.info("step %d: %s", step, records[-1])
                on_validation(records[-1])
            if step % opts.checkpoint_every == 0 and step < opts.iterations:
                checkpoint()
    except KeyboardInterrupt:
        log.warning("interrupted at step %d: writing the resume checkpoint", step)
        checkpoint()
        raise
    finally:
        bar.close()
    if dist.main:
        emit({"step": step, **validate_fn(completer, val_instances, opts.seed)})
        log.info("final validation: %s", records[-1])
        on_validation(records[-1])
    checkpoint(final=True)
    if dist.world > 1:
        torch.distributed.destroy_process_group()
    return {"step": step, "out": str(out), "validation": records[-1] if records else {}}
