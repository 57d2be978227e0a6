"""Train a completion backend self-supervised from partial scans (``pcc train BACKEND``).

The loop is generic. A trainable backend's class (``get_backend(BACKEND)``) owns its recipe:
``cls.training_recipe(size, **options)`` returns a :class:`~pcc_ros.models.recipe.TrainingRecipe`
(the contract: what it must state, what it may override, and in which order this module
calls it). A recipe lives beside its network in ``models/``, which never imports ``data/`` or
this module; :func:`load_recipe` hands it :func:`training_kit` (``models.recipe.TrainingKit``:
the cache loader, TraPCC's ground-truth pools, :func:`validation_instances` and :func:`validate`).

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
from pcc_ros.models.base import select_device
from pcc_ros.models.checkpoint import load_checkpoint, make_config, save_checkpoint, validate_state
from pcc_ros.models.recipe import TrainingKit, TrainingRecipe
from pcc_ros.models.registry import get_backend
from pcc_ros.workflows.evaluate import instances_from_cache, score_backend

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
    max_minutes: float | None = None  # wall-clock budget of the loop: stop there, validate and save as at the end


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


def load_recipe(backend: str, size: str, options: dict[str, Any]) -> TrainingRecipe:
    """The backend's training recipe (``cls.training_recipe``) with the training kit handed over;
    :class:`ConfigError` if it has none or the options are wrong."""
    cls = get_backend(backend)  # ConfigError for unknown names
    try:
        recipe = cls.training_recipe(size=size, **options)  # the base class refuses backends without weights
    except (TypeError, ValueError) as exc:  # an unknown key, or a value a recipe cannot convert
        raise ConfigError(f"backend {backend!r}: invalid training options {sorted(options)}: {exc}") from exc
    if not isinstance(recipe, TrainingRecipe):
        raise ConfigError(f"backend {backend!r}: its recipe {type(recipe).__name__} is not a "
                          "pcc_ros.models.recipe.TrainingRecipe")
    check_option_types(recipe.options, backend)
    recipe.kit = training_kit()
    return recipe


def _accepts(kind: Any, value: Any) -> bool | None:
    """Whether ``value`` fits the annotation ``kind`` (None: a kind this check does not know)."""
    if kind is type(None) or kind is bool:
        return value is None if kind is type(None) else isinstance(value, bool)
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

    main = property(lambda self: self.rank == 0, doc="rank 0: the process that validates and writes")

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
    empty = count <= 0 or len(cache.indices(split)) == 0
    return ([], "none") if empty else instances_from_cache(cache, split, count, seed)


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


def plot_log(records: list[dict[str, Any]], path: Path, title: str, best: dict[str, Any] | None = None,
             select_key: str = "val_cd_l1") -> None:
    """Loss and validation curves against the step as a PNG; none where matplotlib is missing (log.jsonl)."""
    try:
        import matplotlib
    except ImportError:
        return log.info("matplotlib not installed: no %s (the curves are in log.jsonl)", path.name)
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


# --------------------------------------------------------------------------- the run


class TrainingRun:
    """One ``pcc train`` run, in the order :func:`train` drives it: set-up (here), :meth:`resume`,
    :meth:`load_data`, :meth:`loop`, :meth:`finish`; :meth:`save_weights` and :meth:`checkpoint`
    write what the loop produces."""

    def __init__(self, opts: TrainConfig) -> None:
        """Set-up: the recipe, the process group and device, the completer, the optimizer, the run's
        settings (what a resumed run must match) and its output directory."""
        import torch

        if opts.iterations < 1 or opts.batch_size < 1:
            raise ConfigError("--iterations and --batch-size must be >= 1")
        self.opts = opts
        self.dist = Distributed.from_env()
        if opts.threads:
            torch.set_num_threads(opts.threads)
        options = dict(opts.options)
        if not opts.inpainting:
            options["inpainting"] = False
        if opts.stage:
            options["stage"] = opts.stage
        self.recipe = load_recipe(opts.backend, opts.size, options)
        self.device = self._join_process_group(opts.device)
        torch.manual_seed(opts.seed)  # same initial weights on every rank
        self.completer = self.recipe.build_completer(self.device)
        self.init = init_weights(self.completer, opts.init) if opts.init is not None and not opts.resume else None
        self.net = self.completer.model
        self.net.train()
        self.lr = opts.lr if opts.lr is not None else float(self.recipe.default_lr)
        self.decay_every = opts.lr_decay_every or max(1, opts.iterations // 4)
        self.optimizer = torch.optim.Adam(self.net.parameters(), lr=self.lr)
        self.out: Path = opts.out
        self.out.mkdir(parents=True, exist_ok=True)
        self.log_path = self.out / "log.jsonl"
        self.settings: dict[str, Any] = {
            "backend": opts.backend, "config": opts.size, "iterations": opts.iterations,
            "batch_size": opts.batch_size, "world_size": self.dist.world, "lr": self.lr,
            "lr_decay_every": self.decay_every, "seed": opts.seed, "data": str(opts.data), "split": opts.split,
            "recipe": self.recipe.describe(),
        }
        if self.init is not None:
            self.settings["init"] = self.init
        self.step = 0
        self.records: list[dict[str, Any]] = []
        self.select_key = self.recipe.select_metric or f"val_{opts.select_by}"
        self.lower_better = self.select_key != "val_fscore"
        self.started = time.perf_counter()

    def _join_process_group(self, request: str) -> str:
        """The device of this process; under torchrun (``WORLD_SIZE`` > 1) the process group joined first."""
        import torch

        if self.dist.world <= 1:
            return str(select_device(request))
        backend = "nccl" if torch.cuda.is_available() and request != "cpu" else "gloo"
        torch.distributed.init_process_group(backend=backend)
        if backend == "nccl":
            torch.cuda.set_device(self.dist.local_rank)
            return f"cuda:{self.dist.local_rank}"
        return "cpu"

    # ---- resume

    def resume(self) -> None:
        """``--resume``: weights, optimizer, step and log of the saved run (its settings must match);
        without it, an output directory holding a run is refused."""
        opts, out = self.opts, self.out
        if opts.resume:
            self.step, previous = load_resume(out, opts.backend, self.completer, self.optimizer)
            if opts.lr_decay_every is None and "lr_decay_every" in previous:
                # a longer --iterations must not move the decay steps of the run being continued
                self.decay_every = int(previous["lr_decay_every"])
                self.settings["lr_decay_every"] = self.decay_every
            changed = {k: (previous.get(k), v) for k, v in self.settings.items()
                       if k not in ("iterations", "data") and previous.get(k) != v}
            if changed:
                raise ConfigError(f"--resume with different settings than the saved run: {changed}")
            log.info("resumed %s at step %d", out / f"{RESUME_NAME}.safetensors", self.step)
        elif (out / f"{RESUME_NAME}.json").exists():
            raise ConfigError(f"{out} already holds a training run; pass --resume to continue or use another --out")
        elif self.dist.main:
            self.log_path.unlink(missing_ok=True)
        if self.log_path.exists():
            self.records = [json.loads(line) for line in self.log_path.read_text().splitlines() if line.strip()]

    # ---- data

    def load_data(self) -> None:
        """The recipe's training set (real scans mixed in), the validation set, the recipe's preparation."""
        opts, recipe = self.opts, self.recipe
        source = recipe.open_data(opts.data)
        t0 = time.perf_counter()
        if opts.real_data:
            recipe.use_real_data(list(opts.real_data), opts.real_share)
        data = recipe.training_data(source, opts.split, min_points=opts.min_points)
        self.total_views = sum(len(g) for g in data) if isinstance(data, list) else len(data)
        log.info("training data: %d groups, %d observations of split %r (%.1f s)",
                 len(data), self.total_views, opts.split, time.perf_counter() - t0)
        self.data, self.settings["real_data"] = recipe.mix_real_data(data, opts.min_points)
        self.val_data, self.reference = [], "none"
        if self.dist.main:
            self.val_data, self.reference = recipe.validation_data(source, opts.val_split, opts.val_instances,
                                                                   opts.seed)
            log.info("validation: %d instances of split %r against %s", len(self.val_data), opts.val_split,
                     self.reference)
        recipe.prepare(self.completer, self.data, self.val_data, opts.seed)

    # ---- the loop

    def emit(self, record: dict[str, Any]) -> None:
        """Append a record to the log (main process only)."""
        if not self.dist.main:
            return
        self.records.append(record)
        with self.log_path.open("a") as f:
            f.write(json.dumps(record) + "\n")

    def validate(self) -> dict[str, Any]:
        """Validate at the current step and log it."""
        self.emit({"step": self.step, **self.recipe.validate(self.completer, self.val_data, self.opts.seed)})
        return self.records[-1]

    def loop(self) -> None:
        """Steps until ``--iterations``: schedule, batch, loss, update; the log every 50 steps, validation
        every ``--val-every`` (the best weights saved), the resume checkpoint every ``--checkpoint-every``."""
        import torch

        opts, dist = self.opts, self.dist
        train_net: Any = self.net
        if dist.world > 1:
            from torch.nn.parallel import DistributedDataParallel

            ids = [dist.local_rank] if self.device.startswith("cuda") else None
            train_net = DistributedDataParallel(self.net, device_ids=ids)
        # Batch sampling is a pure function of (seed, rank, start step): a resumed run is reproducible.
        rng = np.random.default_rng([opts.seed, dist.rank, self.step])
        batches = self.recipe.batches(self.data, opts.batch_size, self.completer.config, rng)
        if dist.main and self.init is not None and self.step == 0 and self.val_data:
            log.info("initial weights %s: %s", opts.init, self.validate())  # where the initial weights stand
        window: dict[str, list[float]] = {}
        window_start = time.perf_counter()
        log_every = 50
        bar = tqdm(total=opts.iterations, initial=self.step, desc=f"train {opts.backend}", unit="step",
                   disable=not opts.progress or not dist.main)
        try:
            while self.step < opts.iterations and not self.out_of_time():
                current_lr = learning_rate(self.lr, self.step, self.decay_every)
                for group in self.optimizer.param_groups:
                    group["lr"] = current_lr
                batch = next(batches).to(self.completer.device)
                loss, stats = self.recipe.loss(train_net, batch)
                if not torch.isfinite(loss):
                    raise TrainingError(f"{opts.data}: non-finite training loss at step {self.step} ({stats})",
                                        hint="the run diverged: lower --lr or resume from the last checkpoint")
                self.optimizer.zero_grad(set_to_none=True)
                loss.backward()
                self.optimizer.step()
                self.step += 1
                for k, v in stats.items():
                    window.setdefault(k, []).append(v)
                bar.update(1)
                bar.set_postfix(loss=f"{stats['loss']:.4f}")
                if self.step % log_every == 0 or self.step == opts.iterations:
                    seconds = time.perf_counter() - window_start
                    n = len(next(iter(window.values())))
                    self.emit({"step": self.step, "lr": current_lr, **{k: float(np.mean(v)) for k, v in window.items()},
                               "instances_per_s": round(n * opts.batch_size * dist.world / max(seconds, 1e-9), 1)})
                    window, window_start = {}, time.perf_counter()
                if dist.main and opts.val_every and self.step % opts.val_every == 0 and self.step < opts.iterations:
                    log.info("step %d: %s", self.step, self.validate())
                    self.keep_if_best(self.records[-1])
                if self.step % opts.checkpoint_every == 0 and self.step < opts.iterations:
                    self.checkpoint()
        except KeyboardInterrupt:
            log.warning("interrupted at step %d: writing the resume checkpoint", self.step)
            self.checkpoint()
            raise
        finally:
            bar.close()
        if self.step < opts.iterations:
            log.info("--max-minutes %s spent at step %d of %d", opts.max_minutes, self.step, opts.iterations)

    def out_of_time(self) -> bool:
        """``--max-minutes`` spent (a shared or lent machine's budget): the loop ends at this step."""
        budget = self.opts.max_minutes
        return budget is not None and time.perf_counter() - self.started >= 60.0 * budget

    def finish(self) -> dict[str, Any]:
        """The final validation and checkpoint; the process group left."""
        import torch

        if self.dist.main:
            log.info("final validation: %s", self.validate())
            self.keep_if_best(self.records[-1])
        self.checkpoint(final=True)
        if self.dist.world > 1:
            torch.distributed.destroy_process_group()
        return {"step": self.step, "out": str(self.out), "validation": self.records[-1] if self.records else {}}

    # ---- save

    def best_record(self) -> dict[str, Any] | None:
        """The validation record with the best selection metric (step 0, the initial weights, never)."""
        key = self.select_key
        vals = [r for r in self.records if key in r and np.isfinite(r[key]) and r["step"] > 0]
        return None if not vals else (min if self.lower_better else max)(vals, key=lambda r: r[key])

    def save_weights(self, name: str, record: dict[str, Any]) -> None:
        """``OUT/<name>.safetensors`` with the run's settings, the recipe's summaries and ``record``'s metrics."""
        training = {
            **self.settings, "steps": self.step, "groups": len(self.data), "observations": self.total_views,
            "validation_reference": self.reference, "wall_seconds": round(time.perf_counter() - self.started, 1),
            "device": str(self.device), "machine": machine_info(), "selected_by": self.select_key,
            "selected_step": record.get("step", self.step),
        }
        data_summary = self.recipe.data_summary()
        if data_summary:
            training["data_summary"] = data_summary
        with self.recipe.saving(self.completer, self.data):
            training.update(self.recipe.summary())
            self.completer.save(self.out / f"{name}.safetensors", training=training,
                                metrics={k: v for k, v in record.items() if k.startswith("val_")})

    def keep_if_best(self, record: dict[str, Any]) -> None:
        """Save the weights when ``record`` is the best validation so far (the shipped checkpoint is the
        best, not the last)."""
        if self.dist.main and self.best_record() is record:
            self.save_weights(self.opts.backend, record)
            log.info("step %d: best %s so far (%.5f): wrote %s", self.step, self.select_key, record[self.select_key],
                     self.out / f"{self.opts.backend}.safetensors")

    def checkpoint(self, final: bool = False) -> None:
        """The resume checkpoint and the curves' PNG; at the end also the last weights."""
        if not self.dist.main:
            return
        backend = self.opts.backend
        save_resume(self.out, backend, self.completer, self.optimizer, self.step, self.settings)
        if final:
            last_val = next((r for r in reversed(self.records) if self.select_key in r), {})
            self.save_weights(f"{backend}_last", last_val)
            if self.best_record() is None:  # no validation data: the last weights are all there is
                self.save_weights(backend, last_val)
        plot_log(self.records, self.out / "training.png", f"pcc train {backend} ({self.opts.size})",
                 best=self.best_record(), select_key=self.select_key)


def train(opts: TrainConfig) -> dict[str, Any]:
    """Run training as ``opts`` says; returns the final summary (also in the checkpoint)."""
    run = TrainingRun(opts)
    run.resume()
    run.load_data()
    run.loop()
    return run.finish()
