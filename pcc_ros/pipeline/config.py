"""The nodes' parameter table, without ROS: the one place a parameter is defined.

One :class:`ParameterSpec` per ROS parameter — name, type, default, description, range or
choices, and whether it can change while the node runs. Names and defaults come from
:class:`pcc_ros.pipeline.core.PipelineConfig`, :class:`pcc_ros.pipeline.filter.FilterConfig` and
:data:`pcc_ros.pipeline.core.NODE_DEFAULTS`, so the nodes, ``pcc replay`` and the YAML files
cannot disagree. The rclpy host turns each spec into a ``ParameterDescriptor`` (ranges
included); :func:`check_value` applies the same rules in the node core, so every runtime
refuses a bad value with the same reason.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any

from pcc_ros.errors import ConfigError
from pcc_ros.pipeline.core import NODE_DEFAULTS, PipelineConfig
from pcc_ros.pipeline.filter import RULES, SCORE_MAPPINGS, SENSOR_PRESETS, FilterConfig

RELIABILITIES = ("reliable", "best_effort")

DESCRIPTIONS = {
    "backend": "completion backend registered in pcc_ros.models (pointpncnet, input, densify, mirror)",
    "checkpoint": "path of a .safetensors checkpoint; empty = the shipped default of the backend",
    "device": "auto, cpu, cuda or cuda:N (auto = the first GPU when CUDA is available)",
    "half_precision": "network weights and activations in float16 on CUDA, bfloat16 on CPU (learned backends)",
    "classes": "detection class ids to complete (case-insensitive; 'vehicle.car' matches 'car')",
    "min_points": "boxes holding fewer LiDAR points are not completed (and not judged by the filter)",
    "max_instances": "per-frame cap on completed boxes, highest detection score first",
    "box_margin": "metres added to every box side when cropping",
    "ground_margin": "points lower than this many metres above the box bottom are ground",
    "batch_size": "instances per backend batch (the GPU / CPU memory knob of learned backends)",
    "workers": "CPU threads completing shares of a frame's instances, one torch thread each (1: torch's threads); "
               ">= 2 also measures the filter's ground and expected returns beside its rays",
    "decode_density": "folding decoders (pointpncnet, trapcc) decode this many times finer per grid axis: denser "
    "completions (2: 2.25x the points)",
    "include_input_points": "also publish the raw scan points (instance -1, source observed) in the completed cloud",
    "include_observed_points": "partial-preserving output: each completed car's own LiDAR points (its instance, "
    "source = observed) with its generated points",
    "class_thresholds": "per-class detection_threshold, 'Class:threshold' entries separated by commas "
    "(e.g. 'Van:0.6, Truck:0.7'); other classes use detection_threshold",
    "max_box_size": "metres; detections with a longer side are skipped (logged with their id)",
    "max_box_range": "metres; detections whose centre is farther along any axis are skipped",
    "max_box_tilt": "radians of roll / pitch a box may have (dropped, yaw kept); more tilted boxes are skipped",
    "max_crop_work": "per-frame bound on (point, box) pairs, about the points under all box footprints; "
    "lowest-score boxes beyond it are skipped and counted",
    "rule": "filter rule: evidence (calibrated scan evidence, docs/filter.md) | trapcc (shape mismatch + score gate)",
    "w_bias": "evidence rule: logistic bias (pcc calibrate-filter)",
    "w_density": "evidence rule: weight of log((returns in box + 1) / (returns a car would give + 1))",
    "w_free_space": "evidence rule: weight of the log-odds of rays passing through the box core vs ending in it",
    "w_ground_gap": "evidence rule: weight of the box bottom's distance to the local ground (m)",
    "w_score": "evidence rule: weight of the detector score as a logit (after score_mapping)",
    "w_mismatch": "evidence rule: weight of the shape-mismatch score (0 unless calibrated with a car-constrained "
    "backend)",
    "reject_threshold": "evidence rule: detections whose probability of being false exceeds this are rejected",
    "sensor": "evidence rule: LiDAR beam model for the expected returns (hdl64 = KITTI, hdl32 = nuScenes)",
    "filter_backend": "completion backend of the mismatch term ('' = the pipeline's backend)",
    "match_threshold": "shape-mismatch score above which a low-score detection is rejected",
    "detection_threshold": "detections scoring at least this (after score_mapping) are always kept",
    "score_mapping": "identity (scores are probabilities) or sigmoid (scores are logits, e.g. PointRCNN)",
    "mcd_scale": "canonical-units scale of the MCD term of the mismatch score",
    "contour_scale": "scale of the 2D-contour term of the mismatch score",
    "grid_cells": "silhouette grid resolution of the contour term",
    "grid_extent": "canonical half-extent of the silhouette grid",
    "sync_slop": "seconds two stamps may differ to pair a cloud with its detections",
    "queue_size": "unmatched messages kept per input (older ones are dropped and counted)",
    "output_frame": "frame of every output (any frame tf2 can reach at the scan's stamp); empty = the scan's frame",
    "qos.points.reliability": "scan subscription: best_effort (matches any publisher) or reliable",
    "qos.points.depth": "scan subscription: keep-last history depth",
    "qos.detections.reliability": "detections subscription: reliable or best_effort",
    "qos.detections.depth": "detections subscription: keep-last history depth",
    "qos.outputs.reliability": "every output publisher: reliable or best_effort",
    "qos.outputs.depth": "every output publisher: keep-last history depth",
    "scan_timeout": "seconds without a scan while detections arrive before /diagnostics warns (scans lost?)",
}

#: Inclusive numeric ranges (the rclpy host declares them as Integer/FloatingPointRange).
RANGES: dict[str, tuple[float, float]] = {
    "min_points": (1, 100_000),
    "max_instances": (1, 10_000),
    "box_margin": (0.0, 5.0),
    "ground_margin": (0.0, 5.0),
    "batch_size": (1, 4096),
    "workers": (1, 64),
    "decode_density": (1, 8),
    "match_threshold": (0.0, 1.0),
    "detection_threshold": (0.0, 1.0),
    "reject_threshold": (1e-6, 1.0 - 1e-6),
    "mcd_scale": (1e-6, 10.0),
    "contour_scale": (1e-6, 10.0),
    "grid_cells": (2, 256),
    "grid_extent": (0.1, 5.0),
    "sync_slop": (0.0, 10.0),
    "queue_size": (1, 1000),
    "scan_timeout": (0.01, 3600.0),
    "qos.points.depth": (1, 1000),
    "qos.detections.depth": (1, 1000),
    "qos.outputs.depth": (1, 1000),
}

#: Parameters restricted to a fixed set of strings.
CHOICES: dict[str, tuple[str, ...]] = {
    "score_mapping": SCORE_MAPPINGS,
    "rule": RULES,
    "sensor": tuple(SENSOR_PRESETS),
    "qos.points.reliability": RELIABILITIES,
    "qos.detections.reliability": RELIABILITIES,
    "qos.outputs.reliability": RELIABILITIES,
}

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
