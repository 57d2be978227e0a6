"""Completion backends behind one interface.

``create(name, **config)`` / ``load_completer(name, checkpoint, device)`` give a
:class:`Completer`; ``available()`` lists the backends. A backend is one module in this
package with an ``@register("name")`` class (see ``base.py``). Importing this package
does not import torch; learned backends import it when they are used.
"""

from pcc_ros.models.base import (
    Completer,
    SceneContext,
    TorchCompleter,
    available,
    create,
    default_checkpoint,
    get_backend,
    load_completer,
    register,
    resample_cloud,
    select_device,
)

__all__ = [
    "Completer",
    "SceneContext",
    "TorchCompleter",
    "available",
    "create",
    "default_checkpoint",
    "get_backend",
    "load_completer",
    "register",
    "resample_cloud",
    "select_device",
]
