"""Completion backends behind one interface.

``create(name, **config)`` / ``load_completer(name, checkpoint, device)`` give a
:class:`Completer`; ``available()`` lists the backends. The backends are named in one
explicit table, :data:`pcc_ros.models.registry.BACKENDS` (see ``registry.py``); their
interface is ``base.py``. Importing this package does not import torch; learned backends
import it when they are used.
"""

from pcc_ros.models.base import Completer, SceneContext, TorchCompleter, resample_cloud, select_device
from pcc_ros.models.registry import (
    BACKENDS,
    available,
    backend_names,
    create,
    default_checkpoint,
    get_backend,
    load_completer,
    register,
)

__all__ = [
    "BACKENDS",
    "Completer",
    "SceneContext",
    "TorchCompleter",
    "available",
    "backend_names",
    "create",
    "default_checkpoint",
    "get_backend",
    "load_completer",
    "register",
    "resample_cloud",
    "select_device",
]
