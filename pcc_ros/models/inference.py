"""How a completer's network runs at inference: its path, chosen per completer.

A completer (:class:`pcc_ros.models.base.TorchCompleter`) takes ``inference_path`` beside its
``device`` and ``half_precision``; it stores the resolved path on the layers of its own model
(:func:`set_inference_path`), so two completers in one process, and the worker threads of
either, each run their own setting: nothing here is process-wide.

The paths (all give the same values within float rounding; ``pcc bench complete`` times them):

* ``compiled``: the compiled CPU loops (:mod:`pcc_ros.models.kernels`), a network that has a
  one-call kernel (PointPnCNet) in that one call; CPU float32 only;
* ``compiled_layers``: the same loops, the layers called one by one from Python;
* ``operators``: the same chunked steps as torch operators (any device and precision);
* ``reference``: the original path (``torch.segment_reduce`` max-pooling, whole ``(P, C)``
  intermediates), kept for the speed comparison and the equality tests;
* ``auto`` (the default): ``compiled`` where it can run (CPU, float32, numba and SciPy's BLAS
  importable: :func:`kernels_available`), else ``operators``.

The compiled loops' matrix products go to MKL's public CBLAS where it loads, else to SciPy's
BLAS (:mod:`pcc_ros.models.blas`): a capability of the machine, not a setting; both give the
same values within float rounding.
"""

from __future__ import annotations

import functools
import threading
import weakref

import numpy as np
import torch

from pcc_ros.errors import ConfigError

#: The inference paths a completer accepts (see the module doc).
PATHS = ("auto", "compiled", "compiled_layers", "operators", "reference")
#: The paths that run the compiled loops.
COMPILED_PATHS = ("compiled", "compiled_layers")


@functools.cache
def kernels_available() -> bool:
    """Whether the compiled loops can run in this process: numba imports and SciPy's BLAS
    (what numba's ``np.dot`` calls) loads (:data:`pcc_ros.models.kernels.AVAILABLE`)."""
    try:
        from pcc_ros.models import kernels
    except ImportError:
        return False
    return kernels.AVAILABLE


def resolve_path(path: str, device_type: str, half_precision: bool, available: bool | None = None) -> str:
    """``path`` for a completer on ``device_type`` (``cpu`` / ``cuda``), with ``auto`` resolved;
    a :class:`ConfigError` for an unknown path and for a compiled path that cannot run there
    (``available``: :func:`kernels_available` unless given)."""
    if path not in PATHS:
        raise ConfigError(f"inference_path must be one of {', '.join(PATHS)}; got {path!r}")
    available = kernels_available() if available is None else available
    runs_compiled = device_type == "cpu" and not half_precision
    if path == "auto":
        return "compiled" if runs_compiled and available else "operators"
    if path in COMPILED_PATHS:
        if not runs_compiled:
            raise ConfigError(f"inference_path {path!r} runs on the CPU in float32 only (device {device_type}"
                              f"{', half precision' if half_precision else ''}); use auto or operators")
        if not available:
            raise ConfigError(f"inference_path {path!r} needs numba and SciPy's BLAS, which do not load here; "
                              "use auto or operators")
    return path


def set_inference_path(model: torch.nn.Module, path: str) -> int:
    """Store ``path`` on every layer of ``model`` that reads one (an ``inference_path``
    attribute: the PCN encoders, folding decoders, whole networks); returns how many."""
    layers = [m for m in model.modules() if hasattr(m, "inference_path")]
    for module in layers:
        module.inference_path = path
    return len(layers)


def kernels_for(path: str, tensor: torch.Tensor, whole_network: bool = False):
    """The compiled kernels module when a layer on ``path`` may run them on ``tensor`` (CPU,
    float32, the kernels available), else None; ``whole_network``: for a network's single call,
    which ``compiled_layers`` leaves out."""
    if path not in ("auto", *COMPILED_PATHS) or (whole_network and path == "compiled_layers"):
        return None
    if tensor.device.type != "cpu" or tensor.dtype != torch.float32 or not kernels_available():
        return None
    from pcc_ros.models import kernels  # numba: heavy, only for CPU inference

    return kernels


def warm_up_kernels(model: torch.nn.Module) -> None:
    """Compile the compiled CPU loops now (:func:`pcc_ros.models.kernels.warm_up`) when a layer
    of ``model`` runs them (one with ``kernel_weights``, on a compiled path), and a module
    with a ``warm_up_compiled()`` method (a network compiled whole) its own call."""
    layers = [m for m in model.modules() if hasattr(m, "kernel_weights")]
    if not layers or not any(m.inference_path in ("auto", *COMPILED_PATHS) for m in layers):
        return
    if not kernels_available():
        return
    from pcc_ros.models import kernels

    kernels.warm_up()
    for module in model.modules():
        if callable(getattr(module, "warm_up_compiled", None)):
            module.warm_up_compiled()


def as_numpy(t: torch.Tensor) -> np.ndarray:
    """A C-ordered numpy view (or copy) of a CPU tensor, for the compiled kernels."""
    return t.detach().contiguous().numpy()


#: A reused inference buffer (:class:`Workspace`) bigger than this is not kept between calls
#: (the ``paper`` size's wide layers in multi-thread chunks would hold hundreds of MiB).
WORKSPACE_KEEP_BYTES = 16 << 20


class Workspace:
    """Per-thread buffers of the inference paths, kept from call to call.

    A fresh tensor of a few MiB costs page faults on first touch (the kernel maps and zeroes
    its pages) and starts cold in cache; the buffers here are allocated once per (module,
    slot, thread) and reused by every later call of that thread, so the node's worker threads
    never share one. Nothing a forward returns lives here.
    """

    def __init__(self) -> None:
        self._local = threading.local()

    def get(self, owner: torch.nn.Module, slot: str, rows: int, cols: int, like: torch.Tensor) -> torch.Tensor:
        """A ``(rows, cols)`` buffer (contents undefined) for ``owner``'s ``slot``."""
        store = getattr(self._local, "store", None)
        if store is None:
            store = self._local.store = weakref.WeakKeyDictionary()
        slots = store.setdefault(owner, {})
        key = (slot, like.dtype, like.device, torch.is_inference_mode_enabled())
        buf = slots.get(key)
        if buf is None or buf.numel() < rows * cols:
            buf = torch.empty(rows * cols, dtype=like.dtype, device=like.device)
            if buf.numel() * buf.element_size() > WORKSPACE_KEEP_BYTES:  # too big to hold between calls
                slots.pop(key, None)
                return buf.view(rows, cols)
            slots[key] = buf
        return buf[: rows * cols].view(rows, cols)
