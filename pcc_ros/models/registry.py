"""The completion backends, named in one explicit table (as PoinTr's and OpenPCDet's are).

:data:`BACKENDS` maps each name to the ``module:Class`` that implements it; adding a backend
to the package is one line here (its class carries ``@register("name")`` with the same
name, and ``test_models_base`` holds the table and the decorators equal). Modules are
imported when their backend is first asked for, so ``import pcc_ros.models`` never imports
torch. :func:`register` also takes a backend from outside the table at run time (a plugin,
a test's tiny network); :func:`available` lists both.

What a backend knows about itself lives on its class, not in its module:
``cls.presets`` (the named model sizes; the base class checks sizes and builds the defaults
from them), ``cls.training_recipe(size, **options)`` (what ``pcc train`` runs: the module's
recipe function marked ``@Backend.trains_with``; the base class refuses backends without one) and
``cls.weights_name`` (a variant that loads another backend's checkpoints).
"""

from __future__ import annotations

import importlib
import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

from pcc_ros.errors import CheckpointError, ConfigError
from pcc_ros.models.base import Completer
from pcc_ros.paths import share_dirs

log = logging.getLogger(__name__)

#: Every backend of the package: name -> ``"module:Class"``.
BACKENDS: dict[str, str] = {
    "input": "pcc_ros.models.baselines:InputCompleter",
    "mirror": "pcc_ros.models.baselines:MirrorCompleter",
    "densify": "pcc_ros.models.baselines:DensifyCompleter",
    "pointpncnet": "pcc_ros.models.pointpncnet:PointPnCNet",
    "trapcc": "pcc_ros.models.trapcc:TraPCC",
    "aml": "pcc_ros.models.aml.completer:AML",
    "aml_ml": "pcc_ros.models.aml.completer:AMLMaximumLikelihood",
}

#: Classes registered so far (the table's, once imported, and any added at run time).
_REGISTERED: dict[str, type[Completer]] = {}


def register(name: str) -> Callable[[type[Completer]], type[Completer]]:
    """Class decorator: make a :class:`Completer` subclass selectable as ``name``.

    A name of :data:`BACKENDS` is taken only by the class the table names for it.
    """
    if not name or not name.replace("_", "").isalnum() or name != name.lower():
        raise ValueError(f"backend name {name!r} must be lower-case alphanumeric/underscore")

    def decorate(cls: type[Completer]) -> type[Completer]:
        if not (isinstance(cls, type) and issubclass(cls, Completer)):
            raise TypeError(f"@register({name!r}) needs a Completer subclass, got {cls!r}")
        owner = BACKENDS.get(name)
        previous = _REGISTERED.get(name)
        clash = (owner is not None and owner != f"{cls.__module__}:{cls.__qualname__}") or (
            previous is not None and previous.__qualname__ != cls.__qualname__
        )
        if clash:
            holder = owner or f"{previous.__module__}:{previous.__qualname__}"
            raise ValueError(f"backend {name!r} already registered by {holder}")
        cls.name = name
        _REGISTERED[name] = cls
        return cls

    return decorate


def get_backend(name: str) -> type[Completer]:
    """The class of backend ``name`` (its module imported on first use); :class:`ConfigError` if unknown."""
    if name in _REGISTERED:
        return _REGISTERED[name]
    target = BACKENDS.get(name)
    if target is None:
        raise ConfigError(f"unknown completion backend {name!r}; available: {', '.join(available())}")
    module, _, qualname = target.partition(":")
    cls = getattr(importlib.import_module(module), qualname)
    if _REGISTERED.get(name) is not cls:  # the table and the class's @register disagree: a packaging bug
        raise ConfigError(f"backend {name!r}: {target} is not registered under that name (@register({name!r}))")
    return cls


def check_backend_name(name: str) -> None:
    """:class:`ConfigError` (as :func:`get_backend` says it) when no backend is called ``name``,
    without importing a backend module: a pipeline that loads no backend (a filter node whose
    rule gives the shape no weight) still refuses a misspelt ``backend``, without importing torch."""
    if name not in _REGISTERED and name not in BACKENDS:
        get_backend(name)


def backend_names(spec: str, option: str = "--backends", empty_ok: bool = False) -> list[str]:
    """The backends a comma-separated option names (``"input, mirror"``), checked before any work:
    an unknown name is :func:`get_backend`'s one-line :class:`ConfigError` naming the available
    ones; a name given twice is refused too, and an empty list unless ``empty_ok`` (an option
    whose ``""`` means "none")."""
    names = [s.strip() for s in spec.split(",") if s.strip()]
    if not names and not empty_ok:
        raise ConfigError(f"{option} is empty")
    if len(set(names)) != len(names):
        raise ConfigError(f"{option} lists a backend twice: {spec}")
    for name in names:
        get_backend(name)
    return names


def available() -> list[str]:
    """Names of every backend: the table's (those whose module imports) and run-time ones.

    A backend module that fails to import is logged and left out, so one broken backend
    never hides the others.
    """
    names = set(_REGISTERED)
    for name in BACKENDS:
        try:
            get_backend(name)
        except Exception as exc:  # report and keep the others usable
            log.warning("completion backend %r (%s) failed to import: %s", name, BACKENDS[name], exc)
            continue
        names.add(name)
    return sorted(names)


def create(name: str, **config: Any) -> Completer:
    """A fresh backend ``name`` built from ``config`` (untrained weights for learned ones)."""
    cls = get_backend(name)
    try:
        return cls(**config)
    except TypeError as exc:  # an option the constructor does not take
        raise ConfigError(f"backend {name!r}: bad options {sorted(config)}: {exc}") from exc


def default_checkpoint(name: str) -> Path | None:
    """The shipped default checkpoint ``<name>.safetensors`` of a backend, or ``None``.

    Looked up in the package's ``weights/`` directory (package data of a pip/editable
    install) and then in ``<prefix>/share/pcc_ros/weights`` (a colcon install).
    """
    cls = _REGISTERED.get(name)
    if cls is None and name in BACKENDS:
        cls = get_backend(name)
    name = (cls.weights_name if cls is not None else None) or name  # a variant sharing another's weights
    folders = [Path(__file__).resolve().parents[1] / "weights", *(d / "weights" for d in share_dirs())]
    for path in (folder / f"{name}.safetensors" for folder in folders):
        if path.is_file():
            return path
    return None


def load_completer(
    name: str, checkpoint: str | Path | None = None, device: str = "auto", **overrides: Any
) -> Completer:
    """A ready-to-run backend: learned ones with weights loaded, in eval mode.

    Args:
        name: registered backend name.
        checkpoint: ``.safetensors`` path (its ``.json`` beside it); ``None`` uses the
            shipped default for learned backends.
        device: ``auto`` | ``cpu`` | ``cuda`` | ``cuda:N``.
        overrides: run-time options that do not change the weights (``batch_size``, ...).

    Raises:
        CheckpointError: no checkpoint found, or the file is corrupt / mismatched.
        ConfigError: unknown backend, unavailable device, checkpoint given to a baseline.
    """
    cls = get_backend(name)
    if not cls.learned:
        if checkpoint is not None:
            raise ConfigError(f"backend {name!r} has no weights; do not pass a checkpoint")
        return create(name, device=device, **overrides)
    if checkpoint is None:
        checkpoint = default_checkpoint(name)
        if checkpoint is None:
            raise CheckpointError(
                f"no default checkpoint shipped for backend {name!r} (pcc_ros/weights/{name}.safetensors); "
                f"train one with `pcc train {name}` and pass it as the checkpoint"
            )
    return cls.from_checkpoint(checkpoint, device=device, **overrides)
