"""The completion interface every backend implements (the table that names them is
:mod:`pcc_ros.models.registry`).

A backend is a :class:`Completer` subclass decorated with ``@register("name")`` and named
in :data:`pcc_ros.models.registry.BACKENDS`. Callers only ever see
:func:`~pcc_ros.models.registry.create` / :func:`~pcc_ros.models.registry.load_completer`
and :meth:`Completer.complete`.

Contract of :meth:`Completer.complete` (why it is shaped like this):

* input: a batch of *canonical* partial clouds (see ``geometry/canonical.py``), a list of
  ``(N_i, 3)`` arrays of varying size, because real crops never have equal point counts and
  each backend resamples in its own way;
* output: one canonical ``(M_i, 3)`` float32 completion per input, in input order;
* optional scene context (one :class:`SceneContext` or ``None`` per instance) carries the
  neighbouring instances of the same frame, which TraPCC's scene graph needs; backends
  that do not use it ignore it;
* learned backends (:class:`TorchCompleter`) run in chunks of ``batch_size`` under
  ``torch.inference_mode`` on the selected device, in eval mode, and are deterministic:
  any random resampling is seeded per cloud, so a cloud's completion does not depend on
  what else is in the batch.
"""

from __future__ import annotations

import abc
import contextvars
import itertools
import logging
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from pcc_ros.errors import BackendError, CheckpointError, ConfigError, DataError
from pcc_ros.geometry.canonical import to_canonical
from pcc_ros.geometry.sampling import cloud_seed  # re-exported: backends seed per cloud through models.base
from pcc_ros.models.checkpoint import (
    box_aspect_record,
    check_hyper_parameters,
    load_checkpoint,
    make_config,
    parse_box_aspect,
    save_checkpoint,
    validate_state,
)
from pcc_ros.models.recipe import (  # noqa: F401 - re-exported: the backends' recipes build on these
    CacheRecipe,
    CacheTrainOptions,
    TrainingKit,
    TrainingRecipe,
    cache_origin,
    check_held_out,
    median_box_aspect,
)
from pcc_ros.types import Boxes

if TYPE_CHECKING:  # torch is imported lazily so baselines and metrics stay torch-free
    import torch

log = logging.getLogger(__name__)

# --------------------------------------------------------------------------- devices


def select_device(device: str = "auto") -> torch.device:
    """``auto`` -> cuda when available else cpu; an explicit ``cuda`` must be available."""
    import torch

    text = str(device).strip().lower()
    if text == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        chosen = torch.device(text)
    except (RuntimeError, ValueError) as exc:
        raise ConfigError(f"invalid device {device!r}; use auto, cpu, cuda or cuda:N") from exc
    if chosen.type == "cuda":
        if not torch.cuda.is_available():
            raise ConfigError(f"device {device!r} requested but CUDA is not available (use device=auto or cpu)")
        if chosen.index is not None and chosen.index >= torch.cuda.device_count():
            raise ConfigError(f"device {device!r}: only {torch.cuda.device_count()} CUDA device(s)")
    elif chosen.type != "cpu":
        raise ConfigError(f"unsupported device {device!r}; use auto, cpu, cuda or cuda:N")
    return chosen


# --------------------------------------------------------------------------- inputs


@dataclass
class SceneContext:
    """The frame around one instance, for backends that look at neighbours (TraPCC).

    TraPCC's scene graph links an instance to its ``k = 3`` nearest neighbouring vehicles
    within a radius: neighbours seen from the same LiDAR view share its self-occlusion
    pattern, and a neighbour between it and the sensor explains an external occlusion.
    So the context holds the neighbours' points in *their own* canonical frames (shape
    cues) and every box in the sensor frame (where each neighbour is relative to this
    instance and to the sensor).

    Attributes:
        box: this instance's sensor-frame box (one row).
        neighbour_boxes: sensor-frame boxes of the other instances of the frame.
        neighbour_points: canonical ``(N_j, 3)`` clouds of those instances, same order.
        neighbour_sensor_points: optional sensor-frame clouds of the neighbours.
        sensor_origin: sensor position in the sensor frame (the origin unless re-based).
    """

    box: Boxes
    neighbour_boxes: Boxes
    neighbour_points: list[np.ndarray] = field(default_factory=list)
    neighbour_sensor_points: list[np.ndarray] | None = None
    sensor_origin: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self) -> None:
        if len(self.box) != 1:
            raise DataError(f"SceneContext.box must hold exactly one box, got {len(self.box)}")
        if len(self.neighbour_points) != len(self.neighbour_boxes):
            raise DataError(
                f"SceneContext: {len(self.neighbour_points)} neighbour clouds for {len(self.neighbour_boxes)} boxes"
            )
        if self.neighbour_sensor_points is not None and len(self.neighbour_sensor_points) != len(self.neighbour_boxes):
            raise DataError("SceneContext: neighbour_sensor_points and neighbour_boxes disagree in length")
        self.sensor_origin = np.asarray(self.sensor_origin, dtype=np.float64).reshape(3)

    @classmethod
    def from_frame(
        cls,
        boxes: Boxes,
        canonical: Sequence[np.ndarray],
        sensor_points: Sequence[np.ndarray] | None = None,
    ) -> list[SceneContext]:
        """One context per instance of a frame: every other instance is a neighbour."""
        n = len(boxes)
        if len(canonical) != n:
            raise DataError(f"SceneContext.from_frame: {len(canonical)} clouds for {n} boxes")
        contexts = []
        for i in range(n):  # loop over boxes of one frame: a handful
            others = [j for j in range(n) if j != i]
            contexts.append(
                cls(
                    box=boxes[np.array([i])],
                    neighbour_boxes=boxes[np.array(others, dtype=int)],
                    neighbour_points=[canonical[j] for j in others],
                    neighbour_sensor_points=None if sensor_points is None else [sensor_points[j] for j in others],
                )
            )
        return contexts

    def nearest(self, k: int = 3, radius: float = float("inf")) -> SceneContext:
        """The ``k`` nearest neighbours (box-centre distance) within ``radius`` metres."""
        d = np.linalg.norm(self.neighbour_boxes.center - self.box.center[0], axis=1)
        order = np.argsort(d, kind="stable")
        keep = order[d[order] <= radius][:k]
        return SceneContext(
            box=self.box,
            neighbour_boxes=self.neighbour_boxes[keep],
            neighbour_points=[self.neighbour_points[j] for j in keep],
            neighbour_sensor_points=None
            if self.neighbour_sensor_points is None
            else [self.neighbour_sensor_points[j] for j in keep],
            sensor_origin=self.sensor_origin,
        )

    def neighbour_centres_canonical(self) -> np.ndarray:
        """``(K, 3)`` neighbour box centres in this instance's canonical frame."""
        return to_canonical(
            self.neighbour_boxes.center, self.box.center[0], float(self.box.yaw[0]), float(self.box.size[0, 0])
        ).astype(np.float32)


def as_cloud_list(partials: Sequence[np.ndarray] | np.ndarray, what: str = "partial cloud") -> list[np.ndarray]:
    """Validate a batch into a list of C-contiguous float32 ``(N_i, 3)`` arrays.

    Accepts a list of arrays or one ``(B, N, 3)`` array. Extra columns (intensity) are
    dropped. Raises :class:`DataError` naming the offending index on a wrong shape,
    an empty cloud or non-finite coordinates.
    """
    if isinstance(partials, np.ndarray):
        if partials.ndim == 2:
            raise DataError(f"{what}s: got one (N, 3) array; pass a list of clouds or a (B, N, 3) batch")
        if partials.ndim != 3:
            raise DataError(f"{what}s: expected a (B, N, 3) array, got shape {partials.shape}")
        partials = list(partials)
    clouds = []
    for i, cloud in enumerate(partials):
        array = np.asarray(cloud)
        if array.ndim != 2 or array.shape[1] < 3:
            raise DataError(f"{what} {i}: expected shape (N, 3), got {array.shape}")
        if len(array) == 0:
            raise DataError(f"{what} {i} is empty")
        array = np.ascontiguousarray(array[:, :3], dtype=np.float32)
        if not np.isfinite(array).all():
            raise DataError(f"{what} {i} has non-finite coordinates")
        clouds.append(array)
    return clouds


#: Bounds of the per-axis factor of :func:`aspect_scales`: a box more than twice as wide or tall
#: (relative to its length) as the reference is not a car body the reference frame can represent.
ASPECT_SCALE_RANGE = (0.5, 2.0)


def aspect_scales(sizes: np.ndarray, box_aspect: Sequence[float], count: int) -> np.ndarray:
    """Per-cloud factors ``(count, 3)`` that give each canonical box the reference aspect.

    The canonical frame scales by the box *length* only, so a 2.2 m tall van sits in a taller
    canonical box than the SynthCars sedans a network learned from (height / length 0.45 vs
    0.36) and its completion keeps a sedan's height. Multiplying canonical y by
    ``box_aspect[0] / (width / length)`` and z by ``box_aspect[1] / (height / length)`` maps
    every box onto the reference proportions; dividing the output by the same factors maps the
    completion back into the box (exact inverse). Factors are clipped to
    :data:`ASPECT_SCALE_RANGE`. ``sizes``: ``(count, 3)`` length, width, height in metres.
    """
    size = np.asarray(sizes, dtype=np.float64)
    if size.shape != (count, 3):
        raise DataError(f"sizes: expected shape ({count}, 3) (length, width, height per cloud), got {size.shape}")
    if not (np.isfinite(size).all() and (size > 0).all()):
        raise DataError("sizes: box length, width and height must be finite and positive")
    aspect = np.asarray(box_aspect, dtype=np.float64).reshape(2)
    scales = np.ones((count, 3))
    scales[:, 1:] = aspect[None, :] / (size[:, 1:] / size[:, :1])
    return np.clip(scales, *ASPECT_SCALE_RANGE).astype(np.float32)


def resample_cloud(cloud: np.ndarray, n: int, seed: int = 0) -> np.ndarray:
    """Exactly ``n`` points of ``cloud``: a random subset, or all points plus random repeats.

    Seeded from the cloud's own content (:func:`cloud_seed`), so repeated calls, and the
    same cloud in different batches, give identical results.
    """
    rng = np.random.default_rng(cloud_seed(cloud, seed))
    m = len(cloud)
    if m >= n:
        index = rng.choice(m, n, replace=False)
    else:
        index = np.concatenate([rng.permutation(m), rng.integers(0, m, n - m)])
    return cloud[index]


# --------------------------------------------------------------------------- completers


class Completer(abc.ABC):
    """A completion backend: canonical partial clouds in, canonical completions out.

    Subclasses implement :meth:`_complete`; :meth:`complete` validates inputs, aligns the
    scene contexts and checks what the backend returned, so every backend is held to the
    same contract.
    """

    name: ClassVar[str] = ""
    #: Has trainable weights (loaded from a checkpoint).
    learned: ClassVar[bool] = False
    #: Reads :class:`SceneContext` (others ignore it, and callers may skip building it).
    uses_context: ClassVar[bool] = False
    #: Loads the checkpoints of another backend (an inference variant of it); ``None``: its own.
    weights_name: ClassVar[str | None] = None
    #: The output already holds every input point (``input``, ``mirror``): ``keep_input`` adds nothing.
    contains_input: ClassVar[bool] = False
    #: Reference box aspect ``(width / length, height / length)`` the network works in, or ``None``
    #: (see :func:`aspect_scales`); learned backends take it from their checkpoint.
    box_aspect: tuple[float, float] | None = None
    #: Named model sizes (``pcc train --config NAME``, ``size=NAME``): name -> hyper-parameters.
    #: A backend states only this table; the base class checks sizes and builds the defaults from it.
    presets: ClassVar[dict[str, dict[str, Any]]] = {}
    #: ``(size, **options) -> recipe`` of ``pcc train`` (set by :meth:`trains_with`); ``None``: not trainable.
    recipe_factory: ClassVar[Callable[..., Any] | None] = None

    @classmethod
    def check_size(cls, size: str) -> str:
        """``size`` if it names one of :attr:`presets`, else a :class:`ConfigError` listing them."""
        if size not in cls.presets:
            raise ConfigError(f"{cls.name}: unknown size {size!r}; choose from {sorted(cls.presets)}")
        return size

    @classmethod
    def trains_with(cls, factory: Callable[..., Any]) -> Callable[..., Any]:
        """Decorator on a backend module's recipe function: ``pcc train NAME`` runs it (subclasses too)."""
        cls.recipe_factory = staticmethod(factory)
        return factory

    @classmethod
    def training_recipe(cls, size: str = "default", **options: Any) -> Any:
        """What ``pcc train`` runs for this backend: its :attr:`recipe_factory` for a known size;
        backends without one refuse."""
        if cls.recipe_factory is None:
            raise ConfigError(f"backend {cls.name!r} cannot be trained with `pcc train` (no training_recipe)")
        return cls.recipe_factory(size=cls.check_size(size), **options)

    def __init__(self, device: str = "auto", **config: Any) -> None:
        self.device_request = device
        self.config: dict[str, Any] = dict(config)

    def complete(
        self,
        partials: Sequence[np.ndarray] | np.ndarray,
        context: Sequence[SceneContext | None] | SceneContext | None = None,
        *,
        sizes: np.ndarray | None = None,
        keep_input: bool = False,
    ) -> list[np.ndarray]:
        """Complete a batch of canonical partial clouds; returns one float32 cloud each.

        ``sizes``: ``(B, 3)`` box length, width, height in metres, one row per cloud. A backend
        with a :attr:`box_aspect` then completes each cloud in a frame where its box has that
        aspect (:func:`aspect_scales`) and its output is mapped back exactly; without ``sizes``,
        or for backends without an aspect, the clouds go in as they are.

        ``keep_input``: the *partial-preserving* completion, i.e. what ``completion_node``
        publishes (``include_observed_points``): the observed points first, then the generated
        ones (``out[:len(partial)]`` is the partial itself), as PoinTr concatenates its input
        with the predicted missing part. ``False`` gives the network's own shape only (the
        detection filter's shape-mismatch term needs that). Backends whose output already holds
        the input (:attr:`contains_input`) return it unchanged.
        """
        clouds = as_cloud_list(partials)
        if context is None:
            contexts: list[SceneContext | None] = [None] * len(clouds)
        elif isinstance(context, SceneContext):
            if len(clouds) != 1:
                raise DataError("one SceneContext given for a batch; pass one context per cloud")
            contexts = [context]
        else:
            contexts = list(context)
            if len(contexts) != len(clouds):
                raise DataError(f"{len(contexts)} scene contexts for {len(clouds)} clouds")
        if not clouds:
            return []
        scales = None
        if sizes is not None and self.box_aspect is not None:
            scales = aspect_scales(sizes, self.box_aspect, len(clouds))
            outputs = self._complete([np.ascontiguousarray(c * s, dtype=np.float32) for c, s in zip(clouds, scales)],
                                     contexts)
        else:
            outputs = self._complete(clouds, contexts)
        if len(outputs) != len(clouds):
            raise BackendError(f"backend {self.name!r} returned {len(outputs)} clouds for {len(clouds)} inputs")
        result = []
        dropped = 0
        for i, out in enumerate(outputs):
            array = np.asarray(out, dtype=np.float32)
            if array.ndim != 2 or array.shape[1] != 3:
                raise BackendError(f"backend {self.name!r} returned shape {array.shape} for cloud {i}")
            if not np.isfinite(array).all():  # a diverged network must not poison the metrics or the filter
                finite = np.isfinite(array).all(axis=1)  # per point only then: the per-row reduction is the slow one
                dropped += int((~finite).sum())
                array = array[finite]
                if len(array) == 0:
                    raise BackendError(f"backend {self.name!r} returned no finite point for cloud {i}")
            if scales is not None:
                array = array / scales[i]
            if keep_input and not self.contains_input:
                array = np.concatenate([clouds[i], array])
            result.append(np.ascontiguousarray(array, dtype=np.float32))
        if dropped:
            log.warning("backend %r: dropped %d non-finite output points", self.name, dropped)
        return result

    @abc.abstractmethod
    def _complete(self, clouds: list[np.ndarray], contexts: list[SceneContext | None]) -> list[np.ndarray]:
        """Backend work on validated float32 clouds (never empty, all finite)."""

    def __repr__(self) -> str:
        return f"{type(self).__name__}(name={self.name!r}, config={self.config!r})"


#: Largest ``decode_density`` (a 2x2 folding grid becomes 9x9: 20x the points).
MAX_DECODE_DENSITY = 8


def _cast_floating_inputs(dtype):
    """Forward pre-hook: floating-point tensor arguments to ``dtype`` (indices stay integers)."""

    import torch

    def hook(module, args):
        return tuple(a.to(dtype) if torch.is_tensor(a) and a.is_floating_point() else a for a in args)

    return hook


class TorchCompleter(Completer):
    """Base of learned backends: device, batching, eval mode, checkpoint I/O.

    A subclass provides:

    * ``presets`` -> the named sizes (``default`` among them): the constructor's ``size``
      picks one, other keys override it, and ``default_config()`` (``size`` + the ``default``
      preset: the only keys the constructor accepts and checkpoints store) is built from it;
      a backend without presets defines ``default_config()`` itself;
    * a recipe function decorated ``@Backend.trains_with`` (what ``pcc train`` runs,
      through :meth:`Completer.training_recipe`), for a trainable backend;
    * ``build_model()`` -> the ``torch.nn.Module`` for ``self.config``;
    * ``forward_batch(clouds, contexts)`` -> completions of one chunk (at most
      ``batch_size`` clouds), called under ``torch.inference_mode`` with the model in eval
      mode; use :func:`resample_cloud` (content-seeded) if the network needs fixed sizes.

    ``decode_density`` (run-time, default 1): folding decoders (PointPnCNet, TraPCC) decode on a
    grid that many times finer per axis over the same span (``FoldingDecoder.set_density``): the
    trained grid points are kept and the new ones lie between them on each folded patch, so a
    2x2 grid becomes 3x3 at 2 (2.25x the points). ``completion_node`` uses 2 (``decode_density``
    parameter): on real KITTI cars the denser surface covers more of the car (docs/evaluation.md).

    Run-time options that do not change the weights (``batch_size``, ``half_precision``:
    weights and activations in float16 on CUDA, bfloat16 on CPU; inputs are cast on the way
    in, outputs come back as float32; ``workers``) are not hyper-parameters and are not saved.
    ``workers > 1`` (CPU only) splits a call's instances over that many threads, each running
    its share with one intra-op torch thread: parallelism without the per-operator barriers
    of intra-op threads, which stall whenever another process holds a core (``pcc bench
    complete`` / ``pipeline`` measure the settings). While such a call runs, torch's thread
    count is 1 process-wide.

    ``inference_path`` (run-time, default ``auto``): how the network runs
    (:mod:`pcc_ros.models.inference`: the compiled CPU loops where numba and SciPy's BLAS load
    and the network is CPU float32, else torch operators; ``compiled``, ``compiled_layers``,
    ``operators``, ``reference`` by name). It is this completer's own setting, stored on its
    model's layers: completers with different paths, devices and precisions run side by side
    in one process, from any threads; set :attr:`inference_path` between calls to change it.
    """

    learned: ClassVar[bool] = True

    def __init__(
        self, device: str = "auto", batch_size: int = 32, half_precision: bool = False, workers: int = 1,
        box_aspect: Sequence[float] | None = None, decode_density: int = 1, inference_path: str = "auto",
        **config: Any
    ) -> None:
        if self.presets:  # a named size: its preset, then the given overrides
            size = self.check_size(config.pop("size", "default"))
            config = {**self.presets[size], **config, "size": size}
        defaults = self.default_config()
        unknown = sorted(set(config) - set(defaults))
        if unknown:
            raise ConfigError(f"backend {self.name!r}: unknown option(s) {unknown}; known: {sorted(defaults)}")
        if int(batch_size) < 1:
            raise ConfigError(f"batch_size must be >= 1, got {batch_size}")
        if int(workers) < 1:
            raise ConfigError(f"workers must be >= 1, got {workers}")
        if not 1 <= int(decode_density) <= MAX_DECODE_DENSITY:
            raise ConfigError(f"decode_density must be in 1..{MAX_DECODE_DENSITY}, got {decode_density}")
        super().__init__(device=device, **{**defaults, **config})
        self.batch_size = int(batch_size)
        self.half_precision = bool(half_precision)
        self.workers = int(workers)
        self.box_aspect = None if box_aspect is None else parse_box_aspect(box_aspect)
        self._pool = None
        self.device = select_device(device)
        self.model = self.build_model().to(self.device)
        self.decode_density = int(decode_density)
        if self.decode_density > 1:
            from pcc_ros.models.layers import set_decode_density

            set_decode_density(self.model, self.decode_density)
        if self.half_precision:
            import torch

            dtype = torch.float16 if self.device.type == "cuda" else torch.bfloat16
            self.model.to(dtype)  # a checkpoint loaded later is cast by load_state_dict
            self.model.register_forward_pre_hook(_cast_floating_inputs(dtype))
        self.model.eval()
        self._inference_path, self._warmed_up = "auto", False
        self.inference_path = inference_path  # resolved, stored on the layers, compiled loops warmed up
        #: What the weights were trained on, their metrics ... (from a loaded checkpoint).
        self.checkpoint_config: dict[str, Any] | None = None

    @property
    def inference_path(self) -> str:
        """How the network runs (:mod:`pcc_ros.models.inference`), ``auto`` resolved."""
        return self._inference_path

    @inference_path.setter
    def inference_path(self, path: str) -> None:
        from pcc_ros.models.inference import COMPILED_PATHS, resolve_path, set_inference_path, warm_up_kernels

        resolved = resolve_path(path, self.device.type, self.half_precision)
        set_inference_path(self.model, resolved)
        if resolved in COMPILED_PATHS and not self._warmed_up:
            warm_up_kernels(self.model)  # the compiled CPU loops its layers run, before the first batch
            self._warmed_up = True
        self._inference_path = resolved

    @classmethod
    def default_config(cls) -> dict[str, Any]:
        """Hyper-parameters and their defaults (JSON-able values): ``size`` and the ``default``
        preset's (a backend without :attr:`presets` defines its own)."""
        if "default" not in cls.presets:
            raise NotImplementedError(f"{cls.__name__}: give the class presets (with 'default') or a default_config()")
        return {"size": "default", **cls.presets["default"]}

    @abc.abstractmethod
    def build_model(self) -> torch.nn.Module:
        """The network for ``self.config``."""

    @abc.abstractmethod
    def forward_batch(self, clouds: list[np.ndarray], contexts: list[SceneContext | None]) -> list[np.ndarray]:
        """Complete one chunk (under inference mode, model in eval mode)."""

    def _complete(self, clouds: list[np.ndarray], contexts: list[SceneContext | None]) -> list[np.ndarray]:
        if self.model.training:
            self.model.eval()
        workers = min(self.workers, len(clouds))
        if workers > 1 and self.device.type == "cpu":
            return self._complete_threaded(clouds, contexts, workers)
        return self._complete_chunks(clouds, contexts)

    def _complete_chunks(self, clouds: list[np.ndarray], contexts: list[SceneContext | None]) -> list[np.ndarray]:
        import torch

        outputs: list[np.ndarray] = []
        with torch.inference_mode():  # thread-local: entered by every worker thread itself
            for start in range(0, len(clouds), self.batch_size):
                stop = start + self.batch_size
                outputs.extend(self.forward_batch(clouds[start:stop], contexts[start:stop]))
        return outputs

    def _complete_threaded(
        self, clouds: list[np.ndarray], contexts: list[SceneContext | None], workers: int
    ) -> list[np.ndarray]:
        """Contiguous shares of the instances on ``workers`` threads (this one included), in order."""
        import torch

        if self._pool is None or self._pool._max_workers < self.workers - 1:
            self._pool = ThreadPoolExecutor(max_workers=self.workers - 1, thread_name_prefix="pcc-complete")
        bounds = np.linspace(0, len(clouds), workers + 1).round().astype(int).tolist()
        shares = list(itertools.pairwise(bounds))
        previous = torch.get_num_threads()
        torch.set_num_threads(1)
        try:
            # each share in a copy of this thread's context: a line logged there (aml's decoder) is
            # the line of the node whose frame this is (pcc_ros.runtime.node.node_at_work)
            futures = [self._pool.submit(contextvars.copy_context().run, self._complete_chunks, clouds[a:b],
                                         contexts[a:b]) for a, b in shares[1:]]
            a, b = shares[0]
            outputs = self._complete_chunks(clouds[a:b], contexts[a:b])
            for future in futures:
                outputs.extend(future.result())
        finally:
            torch.set_num_threads(previous)
        return outputs

    # ---- checkpoints

    def save(
        self,
        path: str | Path,
        *,
        training: dict[str, Any] | None = None,
        metrics: dict[str, Any] | None = None,
        extra: dict[str, Any] | None = None,
    ) -> Path:
        """Write ``path`` (.safetensors) and its ``.json`` config; returns the weights path."""
        if self.box_aspect is not None and not (extra and "box_aspect" in extra):
            extra = {**(extra or {}), "box_aspect": box_aspect_record(self.box_aspect)}
        config = make_config(self.name, self.config, training=training, metrics=metrics, extra=extra)
        return save_checkpoint(path, self.model.state_dict(), config)

    @classmethod
    def from_checkpoint(cls, path: str | Path, device: str = "auto", **overrides: Any) -> TorchCompleter:
        """Build the backend from a checkpoint's config and load its validated weights."""
        state, config = load_checkpoint(path)
        if config["backend"] not in (cls.name, cls.weights_name):
            raise CheckpointError(f"{path}: checkpoint is for backend {config['backend']!r}, not {cls.name!r}")
        hyper = check_hyper_parameters(config, cls.default_config(), str(path))
        if "box_aspect" not in overrides and config.get("box_aspect") is not None:
            try:
                overrides["box_aspect"] = parse_box_aspect(config["box_aspect"])
            except (ConfigError, DataError) as exc:
                raise CheckpointError(f"{path}: bad box_aspect entry: {exc}") from exc
        try:
            completer = cls(device=device, **hyper, **overrides)
        except ConfigError:
            raise
        except (TypeError, ValueError, RuntimeError) as exc:
            raise CheckpointError(f"{path}: cannot build backend {cls.name!r} from its config: {exc}") from exc
        validate_state(completer.model, state, source=str(path))
        completer.model.load_state_dict(state, strict=True)
        completer.model.eval()
        completer.checkpoint_config = config
        return completer
