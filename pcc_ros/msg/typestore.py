"""The rosbags type store every message in pcc_ros is built from, and a class-neutral constructor.

rosbags ships the ROS 2 Jazzy message set but not ``vision_msgs``; this module registers
the vision_msgs 4.x definitions (the release shipped with Humble, Iron and Jazzy) so that
Detection3DArray can be serialised, written to and read from bags, and hashed (RIHS01)
without a ROS install.

Message classes come in two flavours that share attribute names:

* rosbags dataclasses (tests, bags, `pcc replay`): every field is a required keyword,
  ``uint8[]`` and numeric arrays are ``numpy`` arrays;
* rclpy's generated classes (production): every field has a default, ``uint8[]`` is an
  ``array.array('B')``.

Every builder in :mod:`pcc_ros.msg` takes ``classes: Callable[[str], type] | None`` (a type
name such as ``"sensor_msgs/msg/PointCloud2"`` -> class; ``None`` = rosbags) and goes
through :func:`new_message`, which fills the fields a rosbags dataclass requires but the
caller did not give, and :func:`byte_array`, which hands each flavour the ``uint8[]``
container it expects.
"""

from __future__ import annotations

import array
import copy
import dataclasses
import functools
from collections.abc import Callable
from functools import cache, lru_cache
from typing import Any

import numpy as np
from rosbags.typesys import Stores, get_types_from_msg
from rosbags.typesys import get_typestore as _rosbags_typestore
from rosbags.typesys.store import Typestore

from pcc_ros.errors import MessageError

ClassResolver = Callable[[str], type]

#: vision_msgs 4.x definitions (ros-perception/vision_msgs, ros2 branch). The comments
#: do not influence serialisation or the RIHS01 hash; field names and types do.
VISION_MSGS: dict[str, str] = {
    "vision_msgs/msg/ObjectHypothesis": """
# The unique ID of the object class.
string class_id
# The probability or confidence value of the detected object.
float64 score
""",
    "vision_msgs/msg/ObjectHypothesisWithPose": """
# The object hypothesis (ID and score).
vision_msgs/ObjectHypothesis hypothesis
# The 6D pose of the object hypothesis.
geometry_msgs/PoseWithCovariance pose
""",
    "vision_msgs/msg/BoundingBox3D": """
# The 3D position and orientation of the bounding box center
geometry_msgs/Pose center
# The total size of the bounding box, in meters, surrounding the object's center pose.
geometry_msgs/Vector3 size
""",
    "vision_msgs/msg/Detection3D": """
std_msgs/Header header
# Class probabilities.
ObjectHypothesisWithPose[] results
# 3D bounding box surrounding the object.
BoundingBox3D bbox
# ID used for consistency across multiple detection messages. May be empty.
string id
""",
    "vision_msgs/msg/Detection3DArray": """
std_msgs/Header header
# A list of the detected proposals.
Detection3D[] detections
""",
}


#: tf2_msgs 0.36 (Jazzy) TFMessage: what ``/tf`` and ``/tf_static`` carry. rosbags' Jazzy store has it;
#: the ROS 2 wheels do not, so ``scripts/setup_ros.sh`` builds it into the venv from this text
#: (its RIHS01 hash then equals upstream's, the store's own).
TF2_MSGS: dict[str, str] = {
    "tf2_msgs/msg/TFMessage": """
geometry_msgs/TransformStamped[] transforms
""",
}

#: The message packages ``scripts/setup_ros.sh`` builds into a venv of ROS 2 wheels: package -> definitions.
BUILT_PACKAGES: dict[str, dict[str, str]] = {"vision_msgs": VISION_MSGS, "tf2_msgs": TF2_MSGS}


@lru_cache(maxsize=1)
def get_typestore() -> Typestore:
    """The ROS 2 Jazzy rosbags type store with vision_msgs 4.x registered (built once)."""
    store = _rosbags_typestore(Stores.ROS2_JAZZY)
    types: dict = {}
    for name, text in VISION_MSGS.items():
        types.update(get_types_from_msg(text, name))
    store.register(types)
    return store


def rosbags_classes(name: str) -> type:
    """The rosbags message class for a type name such as ``"sensor_msgs/msg/PointCloud2"``."""
    try:
        return get_typestore().types[name]
    except KeyError:
        raise MessageError(f"unknown message type {name!r} (not in the Jazzy + vision_msgs type store)") from None


def type_hash(name: str) -> str:
    """The RIHS01 type hash of ``name`` (``"RIHS01_<sha256 hex>"``), as ROS 2 Jazzy computes it."""
    if name not in get_typestore().types:
        raise MessageError(f"unknown message type {name!r}")
    return get_typestore().hash_rihs01(name)


def resolve(classes: ClassResolver | None) -> ClassResolver:
    """``classes`` or, when ``None``, :func:`rosbags_classes`."""
    return rosbags_classes if classes is None else classes


def is_rosbags_class(cls: type) -> bool:
    """True for rosbags' generated dataclasses (all fields required, numpy arrays)."""
    return dataclasses.is_dataclass(cls) and isinstance(getattr(cls, "__msgtype__", None), str)


_NUMPY_BASE = {
    "bool": np.bool_,
    "byte": np.uint8,
    "char": np.uint8,
    "int8": np.int8,
    "uint8": np.uint8,
    "int16": np.int16,
    "uint16": np.uint16,
    "int32": np.int32,
    "uint32": np.uint32,
    "int64": np.int64,
    "uint64": np.uint64,
    "float32": np.float32,
    "float64": np.float64,
}


def _default_value(desc: tuple, classes: ClassResolver):
    """Zero value of one rosbags field description (BASE / NAME / ARRAY / SEQUENCE)."""
    kind, rest = desc
    kind = int(kind)
    if kind == 1:  # BASE
        base = rest[0]
        if base == "string":
            return ""
        if base == "bool":
            return False
        return 0.0 if base.startswith("float") else 0
    if kind == 2:  # NAME: a nested message
        return new_message(rest, classes)
    inner, length = rest
    if int(inner[0]) == 1 and inner[1][0] in _NUMPY_BASE:  # numeric array / sequence -> numpy
        return np.zeros(length if kind == 3 else 0, dtype=_NUMPY_BASE[inner[1][0]])
    if kind == 3:  # ARRAY of strings or messages
        return [_default_value(inner, classes) for _ in range(length)]
    return []  # SEQUENCE


@cache
def _rosbags_field_specs(cls: type) -> tuple[tuple[str, tuple], ...] | None:
    """``(dataclass field name, field description)`` of a rosbags class; ``None`` for other classes.

    Computed once per class: building a frame's markers constructs about a thousand
    messages, and looking the definition up every time was most of the encode cost.
    """
    if not is_rosbags_class(cls):
        return None
    defs = get_typestore().fielddefs.get(cls.__msgtype__)
    if defs is None:
        raise MessageError(f"message class {cls.__msgtype__!r} is not in the type store")
    # Dataclass field names are the definition's names after rosbags' keyword escaping.
    return tuple((f.name, desc) for f, (_, desc) in zip(dataclasses.fields(cls), defs[1]))


def _constant(value):
    return lambda: value


@lru_cache(maxsize=512)  # bounded: a caller may pass a fresh resolver (a lambda) per call
def _default_makers(cls: type, resolver: ClassResolver) -> tuple[tuple[str, Callable[[], Any]], ...]:
    """``(field name, zero-argument maker of its zero value)`` of a rosbags class, once per
    class: a frame's markers and detections fill thousands of default fields (a ``Marker``
    has a texture, a mesh file and a lifetime no one sets), and reading the field
    descriptions again for each was most of the encode cost. Every call of a maker returns a
    fresh value (immutable constants, new arrays and messages), as :func:`_default_value` does."""
    makers = []
    for name, desc in _rosbags_field_specs(cls):
        kind, rest = int(desc[0]), desc[1]
        if kind == 1:  # BASE: an immutable constant
            makers.append((name, _constant(_default_value(desc, resolver))))
        elif kind == 2:  # NAME: a nested message, made fresh
            makers.append((name, functools.partial(new_message, rest, resolver)))
        else:
            makers.append((name, functools.partial(_default_value, desc, resolver)))
    return tuple(makers)


def new_message(typename: str, classes: ClassResolver | None = None, **fields):
    """Construct ``typename`` with keyword ``fields`` using the resolved class.

    rosbags dataclasses have no defaults, so missing fields are filled with zero values
    (recursively, from the type store's definition); rclpy classes supply their own.
    """
    resolver = resolve(classes)
    cls = resolver(typename)
    specs = _rosbags_field_specs(cls)
    if specs is not None and len(fields) < len(specs):
        try:
            makers = _default_makers(cls, resolver)
        except TypeError:  # an unhashable resolver: no cache
            makers = _default_makers.__wrapped__(cls, resolver)
        for name, make in makers:
            if name not in fields:
                fields[name] = make()
    return cls(**fields)


def from_template(template, **fields):
    """A shallow copy of the message ``template`` with ``fields`` set: the fast way to make many
    messages of one type that differ in a few fields (a message class fills every default
    sub-message on construction, rclpy's even those given: 5-13 us for a Marker or a hypothesis,
    about 3 us for a copy). The copies share every field not set here with ``template``, list
    fields included: set those each copy may be given more of."""
    message = copy.copy(template)
    for name, value in fields.items():
        setattr(message, name, value)
    return message


def byte_array(cls_or_msg, data: np.ndarray):
    """``data`` (uint8 numpy) as the container a ``uint8[]`` field of this flavour expects.

    rosbags: the numpy array itself. rclpy: ``array.array('B')``, the only type its
    setter takes without checking every element in Python.
    """
    cls = cls_or_msg if isinstance(cls_or_msg, type) else type(cls_or_msg)
    if is_rosbags_class(cls):
        return data
    out = array.array("B")
    out.frombytes(memoryview(np.ascontiguousarray(data, dtype=np.uint8)))
    return out
