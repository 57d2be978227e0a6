"""The training contract of the backends: :class:`TrainingRecipe` (what ``pcc train`` calls),
:class:`TrainingKit` (what a recipe gets from the layers above ``models/``) and
:class:`CacheRecipe` (what the recipes that train on instance caches share).

``models/`` never imports ``data/`` or :mod:`pcc_ros.workflows.train` (docs/ARCHITECTURE.md, layers):
``pcc_ros.workflows.train`` sits above both, builds the kit and hands it to the recipe.
"""

from __future__ import annotations

import abc
import contextlib
import functools
import logging
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from pcc_ros.errors import ConfigError, DataError

if TYPE_CHECKING:
    from pcc_ros.models.base import TorchCompleter

log = logging.getLogger("pcc.train")


@dataclass(frozen=True)
class TrainingKit:
    """What a training recipe uses from the layers beside and above ``models/``.

    ``models/`` never imports ``data/`` or ``pcc_ros.workflows.train`` (docs/ARCHITECTURE.md, layers):
    :mod:`pcc_ros.workflows.train`, which sits above both, builds the kit (``train.training_kit()``) and
    hands it to the recipe (``recipe.kit``) before it opens data; :meth:`require` names the
    recipe when it was not handed one (a recipe used outside ``pcc train``).
    """

    #: ``path -> instance cache`` (``data.instance_cache.InstanceCache.load``).
    open_cache: Callable[[Any], Any]
    #: ``(cache, split, count, seed) -> (instances, reference)`` (``train.validation_instances``).
    validation_instances: Callable[[Any, str, int, int], tuple[list[Any], str]]
    #: ``(completer, instances, seed) -> {val_metric: value}`` (``train.validate``).
    validate: Callable[[Any, list[Any], int], dict[str, float]]
    #: TraPCC's ground-truth pools (``data.gt_pools``): the options' type, ``load_or_build_pools``,
    #: ``load_or_assign``.
    pool_config: Callable[..., Any]
    load_or_build_pools: Callable[..., tuple[Any, Path]]
    load_or_assign: Callable[..., dict[str, np.ndarray]]

    @staticmethod
    def require(kit: TrainingKit | None, who: str) -> TrainingKit:
        """``kit``, or a :class:`ConfigError` naming ``who`` (a recipe used outside ``pcc train``)."""
        if kit is None:
            raise ConfigError(f"{who}: the recipe reads its data through the training layer; set "
                              "recipe.kit = pcc_ros.workflows.train.training_kit() (pcc train does)")
        return kit


class TrainingRecipe(abc.ABC):
    """The contract between a trainable backend and :mod:`pcc_ros.workflows.train` (``pcc train``).

    A backend's recipe function (decorated ``@Backend.trains_with``) returns an instance of a
    subclass. ``pcc_ros.workflows.train`` owns seeds, devices, DistributedDataParallel, the optimizer
    and its schedule, resuming, logging and saving; it calls, in this order:

    1. :meth:`open_data` on ``--data``; :meth:`use_real_data` when ``--real-data`` is given;
    2. :meth:`training_data`, then :meth:`mix_real_data` (the real-scan share of an epoch);
    3. :meth:`validation_data` (main process), :meth:`prepare`;
    4. per step :meth:`batches` (one endless iterator) and :meth:`loss`;
       :meth:`validate` every ``--val-every`` steps and at the end;
    5. per save of the weights: :meth:`describe` (at set-up), :meth:`data_summary`,
       :meth:`saving` around :meth:`summary` and the write.

    The four abstract methods are what every recipe states; the rest have defaults that read
    instance caches through :attr:`kit`, which ``pcc_ros.workflows.train`` sets before any data is opened.
    """

    #: the backend, in errors
    name: ClassVar[str] = ""
    #: Adam's base learning rate when ``pcc train`` is given no ``--lr``
    default_lr: ClassVar[float] = 5e-4
    #: the validation metric that selects the shipped weights (``None``: ``pcc train --select-by``)
    select_metric: str | None = None
    #: the training options, a dataclass whose annotations ``pcc train`` checks every ``--option``
    #: against (``None``: the recipe takes keyword arguments and checks them itself)
    options: Any = None
    #: what the recipe uses from ``data/`` and ``pcc_ros.workflows.train`` (models/ imports neither)
    kit: TrainingKit | None = None
    #: ``--real-data`` caches and ``--real-share`` (:meth:`use_real_data`)
    real_caches: tuple[Any, ...] = ()
    real_share: float = 0.0

    # ---- what every recipe states

    @abc.abstractmethod
    def build_completer(self, device: str) -> TorchCompleter:
        """The completer to train (its network is ``.model``), on ``device``."""

    @abc.abstractmethod
    def training_data(self, source: Any, split: str | None, min_points: int = 10) -> Any:
        """The recipe's training set from an opened source (:meth:`open_data`), partial scans only;
        ``split=None``: every split (a real-scan cache mixed in)."""

    @abc.abstractmethod
    def batches(self, data: Any, batch_size: int, config: dict[str, Any], rng: np.random.Generator) -> Iterator[Any]:
        """An endless iterator of batches (each with ``.to(device)``); ``config``: the model's hyper-parameters."""

    @abc.abstractmethod
    def loss(self, net: Any, batch: Any) -> tuple[Any, dict[str, float]]:
        """``(loss tensor, {name: float})`` of one batch; ``stats["loss"]`` is what the progress bar shows."""

    # ---- defaults

    def describe(self) -> dict[str, Any]:
        """The recipe's settings, stored in the checkpoint (``training.recipe``)."""
        return {}

    def open_data(self, path: Any) -> Any:
        """``--data`` opened: an instance cache, its points checked finite (a damaged cache is a named
        error now, not a NaN loss later)."""
        cache = TrainingKit.require(self.kit, self.name).open_cache(path)
        cache.check_finite()
        return cache

    def use_real_data(self, caches: Sequence[Any], share: float) -> None:
        """``--real-data CACHE ... --real-share S``, told before :meth:`training_data`; by default kept
        for :meth:`mix_real_data`."""
        self.real_caches, self.real_share = tuple(caches), float(share)

    def mix_real_data(self, data: Any, min_points: int) -> tuple[Any, dict[str, Any]]:
        """The training set with the real-scan caches mixed in, and what was mixed (for the checkpoint).

        Default, for a training set that is a list of groups: the real caches' groups
        (:meth:`training_data` of every split) are repeated, as references, until they make up
        ``real_share`` of an epoch: real scans are few.
        """
        if not self.real_caches:
            return data, {"caches": [], "share": 0.0}
        if not isinstance(data, list):
            raise ConfigError(f"backend {self.name!r} takes real-scan caches through its own option, not --real-data")
        share = self.real_share
        if not 0.0 < share < 1.0:
            raise ConfigError(f"--real-share must be in (0, 1), got {share}")
        open_cache = TrainingKit.require(self.kit, self.name).open_cache
        real: list[Any] = []
        per_cache = {}
        for path in self.real_caches:
            groups = self.training_data(open_cache(path), None, min_points=min_points)
            per_cache[str(path)] = {"groups": len(groups), "observations": sum(len(g) for g in groups)}
            real.extend(groups)
        if not real:
            raise ConfigError(f"--real-data {', '.join(map(str, self.real_caches))}: no usable real observations")
        repeats = max(1, int(np.ceil(share * len(data) / ((1.0 - share) * len(real)))))
        mixed = [*data, *(real * repeats)]
        effective = len(real) * repeats / len(mixed)
        log.info("real scans: %d groups x %d repeats = %.1f %% of the training groups", len(real), repeats,
                 100 * effective)
        return mixed, {"caches": per_cache, "groups": len(real), "repeats": repeats, "share_requested": share,
                       "share": round(effective, 4)}

    def validation_data(self, source: Any, split: str, count: int, seed: int) -> tuple[Any, str]:
        """``(validation set, what it is compared against)``: by default a seeded subset of the cache's
        ``split`` with its reference (ground truth or the track's aggregate)."""
        return TrainingKit.require(self.kit, self.name).validation_instances(source, split, count, seed)

    def validate(self, completer: TorchCompleter, val_data: Any, seed: int) -> dict[str, float]:
        """``{"val_<metric>": value}`` on the validation set: by default the evaluation metrics."""
        return TrainingKit.require(self.kit, self.name).validate(completer, val_data, seed)

    def prepare(self, completer: TorchCompleter, data: Any, val_data: Any, seed: int) -> None:  # noqa: B027
        """A step between loading the data and the first batch (default: none)."""

    def data_summary(self) -> dict[str, Any]:
        """What the backend trained on, for the checkpoint's ``training.data_summary`` (empty: not recorded)."""
        return {}

    def summary(self) -> dict[str, Any]:
        """Extra facts for the checkpoint's ``training`` section, read inside :meth:`saving`."""
        return {}

    @contextlib.contextmanager
    def saving(self, completer: TorchCompleter, data: Any) -> Iterator[None]:
        """Around each write of the weights: a recipe that transforms only what is saved (AML's latent
        whitening) does it here and restores the training weights after. Default: nothing."""
        yield


def cache_origin(cache: Any) -> dict[str, Any]:
    """Where an instance cache came from and how it was cropped (its ``pcc extract`` record)."""
    config = cache.index.get("config") or {}
    return {"source": cache.index.get("source"),
            "crop": {k: config.get(k) for k in ("boxes", "margin", "ground_margin", "min_points")}}


def check_held_out(caches: Sequence[Any], held_out: Sequence[str], who: str) -> dict[str, Any]:
    """Refuse caches extracted from a held-out source; what was held out, for the checkpoint.

    A cache's source (its ``pcc extract`` record) is held out when it resolves to, or lies
    inside, one of ``held_out`` (paths; the evaluation's own datasets). ``who`` (the recipe's
    backend) starts the :class:`ConfigError`.
    """
    held = [Path(h).resolve() for h in held_out]
    for c in caches:
        source = cache_origin(c)["source"]
        if source is None:
            continue
        src = Path(source).resolve()
        for h in held:
            if src == h or h in src.parents or src in h.parents:
                raise ConfigError(f"{who}: cache {c.root} was extracted from {source}, which is held out "
                                  f"({h}); train without it")
    return {"sources": [str(h) for h in held], "checked_caches": [str(c.root) for c in caches]}


@dataclass
class CacheTrainOptions:
    """The training options of every recipe that trains on instance caches (PointPnCNet's and
    TraPCC's ``TrainOptions`` extend it; all are stored in the checkpoint's ``training.recipe``)."""

    #: train in the box-aspect frame (:attr:`Completer.box_aspect`, what the pipeline completes in):
    #: every training input and target scaled in y / z so its own box has the median aspect of the
    #: main training data's boxes (:func:`aspect_scales`), that reference recorded in the checkpoint
    box_aspect: bool = False
    #: source datasets (paths) that must not reach training (the real evaluation's own data, e.g.
    #: what ``pcc eval --real`` scores): a cache extracted from one of them is refused
    #: (:func:`check_held_out`); recorded in the checkpoint
    held_out: list[str] = field(default_factory=list)
    #: cap on training input points (``None``: the model's ``max_input_points``): a lower cap makes
    #: CPU training steps cheaper, and the max-pooled encoders care little about density
    input_points: int | None = None
    #: the plane the symmetry options (mirror targets, flips, the symmetry term) reflect across.
    #: ``"box"``: the crop box's x-z plane. ``"label"``: for a crop of a detector's box matched to a
    #: labelled track (``pcc extract --boxes detections``), that track's labelled box's centre plane in
    #: the crop's frame (``InstanceCache.label_planes``), so a completion learns the car's plane from
    #: the returns instead of copying the detector's box error onto the far flank; other crops keep
    #: their box's plane. Uses labelled boxes only, no complete shape (:class:`CarPlanes`).
    mirror_plane: str = "box"

    def __post_init__(self) -> None:
        if self.mirror_plane not in ("box", "label"):
            raise ConfigError(f"mirror_plane must be 'box' or 'label', got {self.mirror_plane!r}")


#: The reflection across the box's x-z plane as a ``(3, 4)`` affine map ``[M | t]``.
BOX_REFLECTION = np.array([[1, 0, 0, 0], [0, -1, 0, 0], [0, 0, 1, 0]], dtype=np.float32)
#: The identity as a ``(3, 4)`` affine map (a car placed where its box is).
IDENTITY = np.eye(3, 4, dtype=np.float32)


def _scaled(r: np.ndarray, t: np.ndarray, scales: np.ndarray) -> np.ndarray:
    """The affine map ``x -> r x + t`` of canonical coordinates, in a frame scaled per axis by
    ``scales`` (the box-aspect scaling): ``[S r S^-1 | S t]``."""
    s = np.asarray(scales, dtype=np.float64)
    return np.concatenate([r * s[:, None] / s[None, :], (s * t)[:, None]], axis=1).astype(np.float32)


def plane_reflection(plane: np.ndarray, scales: np.ndarray) -> np.ndarray:
    """The ``(3, 4)`` reflection across a vertical plane through canonical ``(x, y)`` = ``plane[:2]``
    heading ``plane[2]`` (radians from the box's x axis), in a frame scaled per axis by ``scales``
    (the box-aspect scaling): ``S R S^-1`` with offset ``S t``."""
    x, y, yaw = (float(v) for v in plane)
    n = np.array([-np.sin(yaw), np.cos(yaw), 0.0])
    return _scaled(np.eye(3) - 2.0 * np.outer(n, n), 2.0 * (n[0] * x + n[1] * y) * n, scales)


def plane_placement(plane: np.ndarray, scales: np.ndarray) -> np.ndarray:
    """The ``(3, 4)`` map from the frame of the box whose centre plane is ``plane`` (canonical ``x, y``,
    heading) to the crop's frame, scaled by ``scales`` as :func:`plane_reflection`: a shape centred on
    its own box (a retrieved pseudo ground truth) moved to where that box lies in the crop."""
    x, y, yaw = (float(v) for v in plane)
    c, s = np.cos(yaw), np.sin(yaw)
    return _scaled(np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]), np.array([x, y, 0.0]), scales)


def reflect_points(points: np.ndarray, reflection: np.ndarray) -> np.ndarray:
    """``points`` ``(..., N, C)`` (x, y, z first; other columns kept) mapped by the ``(..., 3, 4)``
    affine ``reflection`` (a reflection or a placement; one per cloud of a batch)."""
    out = np.array(points, copy=True)
    out[..., :3] = points[..., :3] @ np.swapaxes(reflection[..., :3], -1, -2) + reflection[..., None, :, 3]
    return out


@dataclass(frozen=True)
class CarPlanes:
    """Each observation's car plane in its crop's frame (``mirror_plane="label"``): ``planes`` are
    ``InstanceCache.label_planes`` (``(N, 3)`` centre ``x, y`` and yaw; ``0, 0, 0`` the box's own plane,
    NaN unknown). An observation whose plane is its box's, or unknown, reflects across its box's plane."""

    planes: np.ndarray

    @functools.cached_property
    def moved(self) -> np.ndarray:
        """``(N,)`` which observations reflect across a plane other than their box's."""
        return np.isfinite(self.planes).all(1) & (np.abs(self.planes) > 1e-9).any(1)

    def reflection(self, i: int, scales: np.ndarray) -> np.ndarray:
        """Observation ``i``'s ``(3, 4)`` reflection in its frame scaled by ``scales`` (box aspect)."""
        if not self.moved[i]:
            return BOX_REFLECTION
        return plane_reflection(self.planes[i], scales)

    def placement(self, i: int, scales: np.ndarray) -> np.ndarray:
        """Observation ``i``'s :func:`plane_placement` (the identity where its plane is its box's)."""
        return plane_placement(self.planes[i], scales) if self.moved[i] else IDENTITY

    def reflections(self, indices: np.ndarray, scales: np.ndarray) -> np.ndarray:
        """``(len(indices), 3, 4)``: :meth:`reflection` of each of ``indices`` with its row of ``scales``."""
        return np.stack([self.reflection(int(i), s) for i, s in zip(indices, scales)]).reshape(-1, 3, 4)

    def placements(self, indices: np.ndarray, scales: np.ndarray) -> np.ndarray:
        """``(len(indices), 3, 4)``: :meth:`placement` of each of ``indices`` with its row of ``scales``."""
        return np.stack([self.placement(int(i), s) for i, s in zip(indices, scales)]).reshape(-1, 3, 4)

    def record(self, used: np.ndarray) -> dict[str, int]:
        """For the checkpoint's data summary: of the ``used`` observations, how many reflect across their
        labelled box's plane, how many are detections without a labelled box."""
        used = np.asarray(used, dtype=np.int64)
        return {"label": int(self.moved[used].sum()), "unmatched": int((~np.isfinite(self.planes[used]).all(1)).sum())}


class CacheRecipe(TrainingRecipe):
    """What the recipes that train on instance caches share: the size and options, the reference
    aspect of the box-aspect frame, the held-out check, ``describe()`` and ``prepare()``.

    A subclass names its backend (:attr:`name`), adds its own settings to ``describe()`` through
    :meth:`settings`, and calls :meth:`fix_aspect` on its main training data's box sizes
    and :meth:`check_held_out` on every cache it trains from.
    """

    #: the backend, in errors and the held-out check
    name: ClassVar[str] = ""

    def __init__(self, size: str, options: CacheTrainOptions) -> None:
        self.size = size
        self.options = options
        #: the reference aspect (width / length, height / length), from the first training data
        self.aspect: tuple[float, float] | None = None

    def settings(self) -> dict[str, Any]:
        """What ``describe()`` records between the size and the options (a subclass's own)."""
        return {}

    def describe(self) -> dict[str, Any]:
        out = {"size": self.size, **self.settings(), **self.options.__dict__}
        if self.aspect is not None:
            out["reference_aspect"] = list(self.aspect)
        return out

    def aspect_record(self) -> list[float] | None:
        """The reference aspect as the checkpoint's data summary records it."""
        return None if self.aspect is None else list(self.aspect)

    def fix_aspect(self, sizes: np.ndarray) -> tuple[float, float] | None:
        """With ``box_aspect``: the reference aspect, fixed by the first call (the main training data's
        ``(N, 3)`` box ``sizes``) for every cache mixed in later; ``None`` without ``box_aspect``."""
        if self.options.box_aspect and self.aspect is None:
            self.aspect = median_box_aspect(sizes)
        return self.aspect

    def car_planes(self, cache: Any) -> CarPlanes | None:
        """The car planes of ``cache``'s observations with ``mirror_plane="label"`` (``None``: every
        observation reflects across its box's plane)."""
        return CarPlanes(cache.label_planes()) if self.options.mirror_plane == "label" else None

    def check_held_out(self, caches: Sequence[Any]) -> dict[str, Any]:
        """:func:`check_held_out` of ``caches`` against the ``held_out`` option, in this backend's name."""
        return check_held_out(caches, self.options.held_out, self.name)

    def prepare(self, completer: TorchCompleter, data: Any, val_instances: Any, seed: int) -> None:
        """The completer validates (and is saved) in the frame it is trained in."""
        if self.options.box_aspect:
            completer.box_aspect = self.aspect


def median_box_aspect(sizes: np.ndarray) -> tuple[float, float]:
    """The median ``(width / length, height / length)`` of ``(N, 3)`` box sizes (a training set's)."""
    size = np.asarray(sizes, dtype=np.float64).reshape(-1, 3)
    if not len(size):
        raise DataError("median_box_aspect: no boxes")
    return float(np.median(size[:, 1] / size[:, 0])), float(np.median(size[:, 2] / size[:, 0]))
