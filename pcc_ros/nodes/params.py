"""The nodes' parameter tables, without ROS.

One :class:`ParameterSpec` per ROS parameter, generated from
:class:`pcc_ros.pipeline.PipelineConfig` so the nodes, ``pcc replay`` and the YAML files
cannot disagree about names, types or defaults.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any

from pcc_ros.filter import FilterConfig
from pcc_ros.pipeline import NODE_DEFAULTS, PipelineConfig

DESCRIPTIONS = {
    "backend": "completion backend registered in pcc_ros.models (pointpncnet, input, densify, mirror)",
    "checkpoint": "path of a .safetensors checkpoint; empty = the shipped default of the backend",
    "device": "auto | cpu | cuda | cuda:N",
    "classes": "detection class ids to complete (case-insensitive)",
    "min_points": "boxes holding fewer LiDAR points are not completed (and not judged by the filter)",
    "max_instances": "per-frame cap on completed boxes, highest detection score first",
    "box_margin": "metres added to every box side when cropping",
    "ground_margin": "points lower than this many metres above the box bottom are ground",
    "batch_size": "instances per backend batch",
    "include_input_points": "also publish the raw scan points (instance = -1) in the completed cloud",
    "match_threshold": "shape-mismatch score above which a low-score detection is rejected",
    "detection_threshold": "detections scoring at least this (after score_mapping) are always kept",
    "score_mapping": "identity (scores are probabilities) | sigmoid (scores are logits, e.g. PointRCNN)",
    "mcd_scale": "canonical-units scale of the MCD term of the mismatch score",
    "contour_scale": "scale of the 2D-contour term of the mismatch score",
    "grid_cells": "silhouette grid resolution of the contour term",
    "grid_extent": "canonical half-extent of the silhouette grid",
    "sync_slop": "seconds two stamps may differ to pair a cloud with its detections",
    "queue_size": "unmatched messages kept per input (older ones are dropped and counted)",
}



@dataclass(frozen=True)
class ParameterSpec:
    name: str
    default: Any
    description: str

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


def parameter_table(defaults: PipelineConfig | None = None) -> list[ParameterSpec]:
    """Every parameter of the nodes with its default and description."""
    values = {**(defaults or PipelineConfig()).as_parameters(), **NODE_DEFAULTS}
    names = [f.name for f in fields(PipelineConfig) if f.name != "filter"]
    names += [f.name for f in fields(FilterConfig)] + list(NODE_DEFAULTS)
    return [ParameterSpec(n, values[n], DESCRIPTIONS[n]) for n in names]
