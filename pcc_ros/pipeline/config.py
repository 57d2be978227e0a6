"""Configuration, in one place: the parameter table, the YAML files, and the pipeline's config.

One :class:`ParameterSpec` per ROS parameter — name, type, default, description, range or
choices (those three written in :mod:`pcc_ros.pipeline.parameters`), and whether it can
change while the node runs. Names and defaults come from
:class:`PipelineConfig`, :class:`pcc_ros.pipeline.filter.FilterConfig` and
:data:`NODE_DEFAULTS`, so the nodes, ``pcc replay`` and the YAML files cannot disagree.

Every way in goes through this table:

* the rclpy host declares one ROS parameter per spec (a ``ParameterDescriptor`` with the
  range) and hands the values to the node core, which checks them with
  :func:`node_parameters` (:func:`check_value` per parameter) — as it checks run-time changes;
* a YAML parameter file (``config/*.yaml``, ``--config``) is read by :func:`load_file`
  (ROS 2's block rules) and checked by the same :func:`node_parameters`;
  :func:`load_parameters` adds the shipped file of a node and command-line overrides
  (``pcc replay``, ``pcc demo``, the benchmarks);
* :func:`pipeline_config` turns checked node parameters into the :class:`PipelineConfig`
  the pipeline runs with; :meth:`PipelineConfig.from_dict` / ``from_yaml`` are the same path.

So every runtime refuses a bad value with the same reason, and a typo in a file is an error
naming it, never ignored.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from pcc_ros.errors import ConfigError, DataError
from pcc_ros.msg.detections import DetectionLimits
from pcc_ros.paths import resource_dir
from pcc_ros.pipeline.filter import FilterConfig, parse_named_values, whole_rule
from pcc_ros.pipeline.parameters import CHOICES, DESCRIPTIONS, RANGES
from pcc_ros.types import class_mask


@dataclass(frozen=True)
class PipelineConfig:
    """Every knob of the pipeline; the nodes declare one ROS parameter per field."""

    backend: str = "pointpncnet"
    checkpoint: str = ""
    device: str = "auto"
    classes: tuple[str, ...] = ("Car", "Van")
    min_points: int = 20
    max_instances: int = 32
    box_margin: float = 0.1
    ground_margin: float = 0.05
    half_precision: bool = False
    batch_size: int = 32
    workers: int = 2
    #: folding decoders decode this many times finer per grid axis (TorchCompleter.decode_density)
    decode_density: int = 2
    include_input_points: bool = False
    #: partial-preserving output: each completed car's own crop points (source observed) with
    #: its generated points, i.e. ``Completer.complete(..., keep_input=True)`` in the sensor frame
    include_observed_points: bool = True
    class_thresholds: str = ""
    #: detector class ids -> names before ``classes`` and ``class_thresholds`` match them
    #: (numeric ids of OpenPCDet / mmdetection3d wrappers), see :func:`parse_class_map`
    class_map: str = ""
    max_box_size: float = 40.0
    max_box_range: float = 1000.0
    max_box_tilt: float = 0.35
    max_crop_work: int = 100_000
    #: track-level completion (pipeline/track_memory.py): complete each car from its crops of the last
    #: track_max_age seconds, same Detection3D.id or, without ids, the nearest box within track_gate metres
    track_memory: bool = False
    track_max_age: float = 1.0
    track_gate: float = 2.0
    filter: FilterConfig = field(default_factory=FilterConfig)

    def __post_init__(self) -> None:
        if self.min_points < 1 or self.max_instances < 1 or self.batch_size < 1 or self.workers < 1:
            raise ConfigError("min_points, max_instances, batch_size and workers must be >= 1")
        if self.max_crop_work < 1:
            raise ConfigError("max_crop_work must be >= 1")
        if self.box_margin < 0 or self.ground_margin < 0:
            raise ConfigError("box_margin and ground_margin must be >= 0")
        if not 1 <= self.decode_density <= 8:
            raise ConfigError(f"decode_density must be in 1..8, got {self.decode_density}")
        object.__setattr__(self, "classes", tuple(str(c) for c in self.classes))
        parse_class_thresholds(self.class_thresholds)  # refuse a malformed map now, not per frame
        parse_class_map(self.class_map)
        self.detection_limits()  # refuse implausible box bounds now, not per frame

    def detection_limits(self):
        """The :class:`~pcc_ros.msg.detections.DetectionLimits` incoming detections must meet."""
        return DetectionLimits(
            max_size=float(self.max_box_size), max_range=float(self.max_box_range),
            max_tilt=float(self.max_box_tilt),
        )

    def map_labels(self, labels: np.ndarray) -> np.ndarray:
        """``labels`` with the class ids ``class_map`` names replaced by their names (others as given)."""
        mapping = parse_class_map(self.class_map)
        if not mapping or not len(labels):
            return labels
        return np.array([mapping.get(class_id_key(v), v) for v in labels], dtype=object)

    def detection_thresholds(self, labels: np.ndarray) -> np.ndarray:
        """The filter's detection-score threshold of each label: ``class_thresholds`` where it
        names the class (same matching as ``classes``), ``filter.detection_threshold`` elsewhere."""
        out = np.full(len(labels), float(self.filter.detection_threshold))
        for name, threshold in parse_class_thresholds(self.class_thresholds).items():
            out[class_mask(labels, (name,))] = threshold
        return out

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> PipelineConfig:
        """From flat node parameters (a YAML ``ros__parameters`` block, ROS parameters, CLI),
        checked against the parameter table (:func:`node_parameters`: an unknown key, a wrong
        type or a value out of range is a :class:`ConfigError` naming the parameter)."""
        return pipeline_config(node_parameters(values))

    @classmethod
    def from_yaml(cls, path: str | Path, node_name: str | None = None) -> PipelineConfig:
        """Read a ``config/*.yaml`` node parameter file (the first node when no name is given)."""
        return pipeline_config(load_file(path, node_name))

    def as_parameters(self) -> dict[str, Any]:
        """Flat parameter dict (the inverse of :meth:`from_dict`)."""
        out = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "filter"}
        out["classes"] = list(self.classes)
        out.update({f.name: getattr(self.filter, f.name) for f in fields(FilterConfig)})
        return out


#: Parameters the node shells read themselves (pairing, queues), with their defaults; the
#: pipeline ignores them (and ROS's own ``use_sim_time``).
NODE_DEFAULTS: dict[str, Any] = {
    "sync_slop": 0.05,
    "queue_size": 2,
    "output_frame": "",
    "qos.points.reliability": "best_effort",
    "qos.points.depth": 5,
    "qos.detections.reliability": "reliable",
    "qos.detections.depth": 10,
    "qos.outputs.reliability": "reliable",
    "qos.outputs.depth": 10,
    "scan_timeout": 1.0,
    "tf_timeout": 0.5,
}
#: Parameters every ROS node has, or rclpy adds itself; never reported as unknown.
ROS_OWN_PARAMETERS = ("use_sim_time", "start_type_description_service")


def parse_class_thresholds(text: str) -> dict[str, float]:
    """``"Van:0.6, Pedestrian:0.3"`` -> ``{"Van": 0.6, "Pedestrian": 0.3}`` (``""`` -> ``{}``).

    Raises :class:`ConfigError` naming the bad entry (no colon, not a number, outside [0, 1]).
    """
    return parse_named_values(text, "class_thresholds", "Class:threshold", "Van:0.6, Truck:0.7")


def integer_id(value) -> str | None:
    """``"1"``, ``" 1 "``, ``"1.0"``, ``"+1"`` -> ``"1"``: a class id that is an integer written any
    way a wrapper may write it (``str()`` of a numpy float label gives ``"1.0"``); None otherwise."""
    try:
        number = float(str(value).strip())
    except ValueError:
        return None
    return str(int(number)) if np.isfinite(number) and number.is_integer() else None


def class_id_key(value) -> str:
    """The key ``class_map`` looks a class id up by: the integer for a numeric id, else the id stripped."""
    return integer_id(value) or str(value).strip()


def parse_class_map(text: str) -> dict[str, str]:
    """``"1:Car, 2:Pedestrian"`` -> ``{"1": "Car", "2": "Pedestrian"}`` (``""`` -> ``{}``): the
    detector's class ids (e.g. the numeric labels of OpenPCDet / mmdetection3d ROS wrappers) and
    the names ``classes`` and ``class_thresholds`` know them by.

    Raises :class:`ConfigError` naming the bad entry (no colon, an empty id or name, an id
    given two different names).
    """
    out: dict[str, str] = {}
    for entry in str(text).split(","):
        entry = entry.strip()
        if not entry:
            continue
        class_id, sep, name = (part.strip() for part in entry.partition(":"))
        if not sep or not class_id or not name or ":" in name or out.get(class_id_key(class_id), name) != name:
            raise ConfigError(
                f"class_map: bad entry {entry!r}; expected 'id:Name' entries separated by commas, each id once "
                "(e.g. '1:Car, 2:Pedestrian, 3:Cyclist' for OpenPCDet's KITTI labels)"
            )
        out[class_id_key(class_id)] = name
    return out


def read_parameters(path: str | Path, node_name: str | None = None) -> dict[str, Any]:
    """The ``ros__parameters`` of one node in a ROS 2 YAML parameter file, dotted names.

    As ROS 2 does, the blocks that apply to the node are merged, most specific last:
    ``/**``, ``/**/<node>``, ``<node>`` and ``/<node>`` (the shipped files use
    ``/**/<node>`` so they apply under any namespace). Without ``node_name`` the first
    block of the file is read.
    """
    path = Path(path)
    return _node_block(_read_document(path), path, node_name)


def _read_document(path: Path) -> dict[str, Any]:
    """A parameter file's YAML: a non-empty map of node blocks, or a :class:`ConfigError` naming the file."""
    try:
        document = yaml.safe_load(path.read_text()) or {}
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read parameter file ({exc.strerror or exc}) — check the path") from exc
    except UnicodeDecodeError as exc:  # a binary file (an image, a bag) where the YAML belongs
        raise ConfigError(f"{path}: cannot read parameter file (not UTF-8 text: {exc.reason} at byte "
                          f"{exc.start}) — check the path") from exc
    except yaml.YAMLError as exc:  # one line: where and what, not PyYAML's multi-line report
        mark = getattr(exc, "problem_mark", None)
        raise ConfigError(f"{path}{f':{mark.line + 1}:{mark.column + 1}' if mark else ''}: not valid YAML "
                          f"({getattr(exc, 'problem', None) or ' '.join(str(exc).split())}) — fix the file") from exc
    if not isinstance(document, dict) or not document:
        raise ConfigError(f"{path}: no node in parameter file")
    return document


def _block_keys(node_name: str) -> list[str]:
    """The keys of a parameter file that apply to ``node_name``, least specific first."""
    return ["/**", f"/**/{node_name}", node_name, f"/{node_name}"]


def _node_block(document: dict[str, Any], path: Path, node_name: str | None) -> dict[str, Any]:
    """:func:`read_parameters` of a parsed file."""
    if node_name is None:
        keys = [next(iter(document))]
        node_name = keys[0].rsplit("/", 1)[-1]
    else:
        keys = _block_keys(node_name)
    values: dict[str, Any] = {}
    found = False
    for key in keys:
        block = document.get(key)
        if block is None:
            continue
        if not isinstance(block, dict) or not isinstance(block.get("ros__parameters"), dict):
            raise ConfigError(f"{path}: '{key}' has no 'ros__parameters:' map")
        values.update(flatten_parameters(block["ros__parameters"]))
        found = True
    if not found:
        raise ConfigError(f"{path}: no '/**/{node_name}: ros__parameters:' block (nodes: {sorted(document)})")
    return values


def flatten_parameters(values: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """Nested YAML maps -> dotted ROS parameter names (``qos: {points: {depth: 5}}`` ->
    ``qos.points.depth``), as ROS 2 reads a parameter file."""
    out: dict[str, Any] = {}
    for key, value in values.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            out.update(flatten_parameters(value, f"{name}."))
        else:
            out[name] = value
    return out


#: Fixed once the node runs (subscriptions, publishers and queues are built from them):
#: declared read-only, a change is refused with "restart the node".
READ_ONLY = frozenset({"queue_size", "scan_timeout", *(name for name in NODE_DEFAULTS if name.startswith("qos."))})

#: Parameters that change the loaded network (a run-time change reloads the backend).
BACKEND_PARAMETERS = ("backend", "checkpoint", "device", "half_precision", "batch_size", "workers", "decode_density")


@dataclass(frozen=True)
class ParameterSpec:
    name: str
    default: Any
    description: str
    range: tuple[float, float] | None = None
    choices: tuple[str, ...] | None = None
    read_only: bool = False

    @property
    def type_name(self) -> str:
        """ROS parameter type: bool, integer, double, string or string_array."""
        value = self.default
        if isinstance(value, bool):
            return "bool"
        if isinstance(value, int):
            return "integer"
        if isinstance(value, float):
            return "double"
        if isinstance(value, (list, tuple)):
            return "string_array"
        return "string"

    @property
    def constraints(self) -> str:
        """The rule as one line of text (``ParameterDescriptor.additional_constraints``)."""
        if self.range is not None:
            return f"{self.range[0]} <= value <= {self.range[1]}"
        if self.choices is not None:
            return "one of " + ", ".join(self.choices)
        return ""


def parameter_table(defaults: PipelineConfig | None = None) -> list[ParameterSpec]:
    """Every parameter of the nodes with its default, description and rule."""
    values = {**(defaults or PipelineConfig()).as_parameters(), **NODE_DEFAULTS}
    names = [f.name for f in fields(PipelineConfig) if f.name != "filter"]
    names += [f.name for f in fields(FilterConfig)] + list(NODE_DEFAULTS)
    return [
        ParameterSpec(
            n, values[n], DESCRIPTIONS[n], range=RANGES.get(n), choices=CHOICES.get(n), read_only=n in READ_ONLY
        )
        for n in names
    ]


def parameter_specs() -> dict[str, ParameterSpec]:
    """:func:`parameter_table` by name."""
    return {spec.name: spec for spec in parameter_table()}


def check_value(spec: ParameterSpec, value: Any) -> Any:
    """``value`` as the parameter's type, or :class:`ConfigError` saying why it is refused.

    The rules are ROS's: no implicit conversion, except that an integer is accepted for a
    double (YAML writes ``1`` for ``1.0``) and a tuple for a string array.
    """
    kind = spec.type_name
    bad = ConfigError(f"parameter '{spec.name}' must be {_ARTICLE[kind]}, got {value!r} ({type(value).__name__})")
    if kind == "bool":
        if not isinstance(value, bool):
            raise bad
    elif kind == "integer":
        if isinstance(value, bool) or not isinstance(value, int):
            raise bad
    elif kind == "double":
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise bad
        value = float(value)
    elif kind == "string_array":
        if isinstance(value, str) or not isinstance(value, (list, tuple)) or not all(isinstance(v, str) for v in value):
            raise bad
        value = list(value)
    elif not isinstance(value, str):
        raise bad
    if spec.range is not None:
        low, high = spec.range
        if not low <= value <= high:  # NaN fails too
            raise ConfigError(f"parameter '{spec.name}' = {value!r} is outside [{low}, {high}]")
    if spec.choices is not None and value not in spec.choices:
        raise ConfigError(f"parameter '{spec.name}' = {value!r} is not one of {list(spec.choices)}")
    return value


_ARTICLE = {
    "bool": "a bool",
    "integer": "an integer",
    "double": "a number",
    "string": "a string",
    "string_array": "a list of strings",
}


def markdown_table() -> str:
    """The parameter table as docs/nodes.md shows it (a test keeps the doc equal to this)."""
    rows = [
        "| parameter | type | default | rule | at run time | description |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for spec in parameter_table():
        default = spec.default
        if isinstance(default, (list, tuple)):
            shown = "[" + ", ".join(default) + "]"
        elif isinstance(default, bool):
            shown = str(default).lower()
        elif isinstance(default, str):
            shown = f'"{default}"'
        else:
            shown = str(default)
        live = "yes, reloads the backend" if spec.name in BACKEND_PARAMETERS else "yes"
        live = "no (read-only)" if spec.read_only else live
        rule = spec.constraints or "-"
        rows.append(f"| `{spec.name}` | {spec.type_name} | `{shown}` | {rule} | {live} | {spec.description} |")
    return "\n".join(rows)


# --------------------------------------------------------------------------- checking and loading


def unknown_parameters(names) -> list[str]:
    """The names in ``names`` that are not parameters of the nodes (ROS's own and rclpy's
    ``qos_overrides.*`` excluded), sorted: a YAML typo must be reported, not ignored."""
    table = {spec.name for spec in parameter_table()}
    return sorted(
        n for n in set(names) - table if n not in ROS_OWN_PARAMETERS and not n.startswith("qos_overrides.")
    )


def node_parameters(values: dict[str, Any] | None = None, overrides: dict[str, Any] | None = None) -> dict[str, Any]:
    """Every node parameter: the defaults of the parameter table overridden by ``values``, then
    by ``overrides`` (both checked, e.g. a file's values and the command line's).

    Each value is checked against its spec (type, range, choices); an unknown name or a bad
    value raises :class:`ConfigError` naming the parameter.
    """
    specs = parameter_specs()
    layers = [{k: v for k, v in (given or {}).items() if k not in ROS_OWN_PARAMETERS} for given in (values, overrides)]
    unknown = unknown_parameters([name for layer in layers for name in layer])
    if unknown:
        raise ConfigError(f"unknown node parameter(s): {unknown} (see docs/nodes.md for the list)")
    merged = {name: spec.default for name, spec in specs.items()}
    for layer in layers:
        merged.update({name: check_value(specs[name], value) for name, value in layer.items()})
    merged["classes"] = list(merged["classes"])
    merged.update(whole_rule({name for layer in layers for name in layer}))
    return merged


def changed_parameters(current: dict[str, Any], changes: dict[str, Any]) -> dict[str, Any]:
    """The checked values of ``changes`` that differ from ``current``, as a running node takes a
    change: an unknown name, a bad value or a read-only parameter (fixed once the node runs) is a
    :class:`ConfigError` naming it, and then nothing of ``changes`` applies."""
    unknown = unknown_parameters(changes)
    if unknown:
        raise ConfigError(f"unknown parameter(s) {unknown}")
    specs = parameter_specs()
    checked = {name: check_value(specs[name], value) for name, value in changes.items()}
    changed = {name: value for name, value in checked.items() if value != current[name]}
    fixed = sorted(name for name in changed if specs[name].read_only)
    if fixed:
        raise ConfigError(f"{fixed} cannot change while the node runs: restart the node")
    return changed


def pipeline_config(values: dict[str, Any]) -> PipelineConfig:
    """The :class:`PipelineConfig` of checked node parameters (:func:`node_parameters`); the
    node-only ones (pairing, QoS, frames) are left to the node."""
    own = {f.name for f in fields(PipelineConfig)} - {"filter"}
    filter_keys = {f.name for f in fields(FilterConfig)}
    main = {k: v for k, v in values.items() if k in own}
    if "classes" in main:
        main["classes"] = tuple(main["classes"])
    return PipelineConfig(**main, filter=FilterConfig(**{k: v for k, v in values.items() if k in filter_keys}))


#: The node of each mode and its shipped parameter file (``config/`` of a checkout,
#: ``share/pcc_ros/config`` of an install).
NODE_NAMES = {"completion": "completion_node", "filter": "detection_filter_node"}
CONFIG_FILES = {"completion": "completion.yaml", "filter": "detection_filter.yaml"}


def shipped_config_dir() -> Path:
    """``config/`` of a source checkout, or ``share/pcc_ros/config`` of an install."""
    folder = resource_dir("config")
    if folder is None:
        raise DataError("cannot find the shipped config/ folder; pass --config")
    return folder


def load_file(path: str | Path, node_name: str | None = None) -> dict[str, Any]:
    """The checked node parameters of a YAML parameter file (its ``node_name`` blocks when the
    file has them, else its first block); errors name the file."""
    return _checked_file(Path(path), node_name)


def _checked_file(path: Path, node_name: str | None, overrides: dict[str, Any] | None = None) -> dict[str, Any]:
    """:func:`load_file` with ``overrides`` on top of the file's values, every value checked once."""
    document = _read_document(path)
    if node_name and not any(key in document for key in _block_keys(node_name)):
        node_name = None  # a file without the node's blocks: its first block
    values = _node_block(document, path, node_name)
    try:
        return node_parameters(values, overrides)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from exc


def load_parameters(config: str | Path | None = None, with_filter: bool = False, **overrides) -> dict[str, Any]:
    """Checked node parameters of the completion node (``with_filter``: the filter node) from a
    YAML file (default: the shipped one) plus ``overrides`` (``None`` values ignored).

    Every value goes through the nodes' own parameter check, so a file a node would refuse
    (unknown key, wrong type, value out of range) is refused here with the same message, also
    where an override replaces the bad value.
    """
    mode = "filter" if with_filter else "completion"
    path = Path(config) if config is not None else shipped_config_dir() / CONFIG_FILES[mode]
    return _checked_file(path, NODE_NAMES[mode], {k: v for k, v in overrides.items() if v is not None})


def load_config(
    config: str | Path | None = None, with_filter: bool = False, **overrides
) -> tuple[PipelineConfig, float]:
    """The :class:`PipelineConfig` and ``sync_slop`` of :func:`load_parameters`."""
    values = load_parameters(config, with_filter, **overrides)
    return pipeline_config(values), float(values["sync_slop"])
