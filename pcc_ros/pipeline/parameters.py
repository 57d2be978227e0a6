"""What each node parameter means: its description, its numeric range or its choices.

The words and rules of the parameter table, kept apart from :mod:`pcc_ros.pipeline.config`
(which joins them with the defaults of :class:`~pcc_ros.pipeline.config.PipelineConfig` into
one :class:`~pcc_ros.pipeline.config.ParameterSpec` per parameter, and checks and loads
values): a new parameter gets its description here, and a range or choices when it has one.
"""

from __future__ import annotations

from pcc_ros.pipeline.beam_model import AUTO
from pcc_ros.pipeline.evidence_profile import PROFILE_TERM_DOCS
from pcc_ros.pipeline.filter import RULES, SCORE_MAPPINGS, SENSOR_PRESETS

#: The QoS reliabilities a ``qos.*.reliability`` parameter takes.
RELIABILITIES = ("reliable", "best_effort")

#: One line a parameter: the ROS ParameterDescriptor's description and docs/nodes.md's table.
DESCRIPTIONS = {
    "backend": "completion backend (pcc_ros.models registry: pointpncnet, trapcc, aml, aml_ml, input, densify, mirror)",
    "checkpoint": "path of a .safetensors checkpoint; empty = the shipped default of the backend",
    "device": "auto, cpu, cuda or cuda:N (auto = the first GPU when CUDA is available)",
    "half_precision": "network weights and activations in float16 on CUDA, bfloat16 on CPU (learned backends)",
    "classes": "detection class ids to complete (case-insensitive; 'vehicle.car' matches 'car')",
    "min_points": "boxes holding fewer LiDAR points are not completed (and not judged by the filter)",
    "max_instances": "per-frame cap on completed boxes, highest detection score first",
    "box_margin": "metres added to every box side when cropping",
    "ground_margin": "points lower than this many metres above the bottom of the box grown by box_margin are ground "
                     "(the defaults 0.05 and 0.1 keep returns from 5 cm below the box bottom up)",
    "batch_size": "instances per backend batch (the GPU / CPU memory knob of learned backends)",
    "workers": "CPU threads completing shares of a frame's instances, one torch thread each (1: torch's threads); "
               "the filter measures on as many (2 or more: its ground and expected returns beside its rays)",
    "decode_density": "folding decoders (pointpncnet, trapcc) decode this many times finer per grid axis: denser "
    "completions (2: 2.25x the points)",
    "include_input_points": "also publish the raw scan points (instance -1, source observed) in the completed cloud",
    "include_observed_points": "partial-preserving output: each completed car's own LiDAR points (its instance, "
    "source = observed) with its generated points",
    "class_map": "detector class ids -> names, 'id:Name' entries separated by commas (e.g. '1:Car, 2:Pedestrian, "
    "3:Cyclist' for OpenPCDet's KITTI model); applied before classes and class_thresholds match; '' = ids as given",
    "class_thresholds": "per-class detection_threshold, 'Class:threshold' entries separated by commas "
    "(e.g. 'Van:0.6, Truck:0.7'); other classes use detection_threshold",
    "max_box_size": "metres; detections with a longer side are skipped (logged with their id)",
    "max_box_range": "metres; detections whose centre is farther along any axis are skipped",
    "max_box_tilt": "radians of roll / pitch a box may have (dropped, yaw kept); more tilted boxes are skipped",
    "max_crop_work": "per-frame bound on (point, box) pairs, about the points under all box footprints; "
    "lowest-score boxes beyond it are skipped and counted",
    "track_memory": "complete each car from its accumulated crops of the last track_max_age seconds (same "
    "Detection3D.id, or the nearest box within track_gate metres when ids are empty); off: each frame alone",
    "track_max_age": "track_memory: seconds a car's past crops are kept (an id unseen this long is freed)",
    "track_gate": "track_memory without ids: metres a box centre may move between frames and stay the same car",
    "rule": "filter rule: evidence (calibrated scan evidence, docs/filter.md) | trapcc (shape mismatch + score gate)",
    "w_bias": "evidence rule: logistic bias (pcc calibrate-filter)",
    "w_density": "evidence rule: weight of log((returns in box + 1) / (returns a car would give + 1))",
    "w_free_space": "evidence rule: weight of the log-odds of rays passing through the box core vs ending in it",
    "w_ground_gap": "evidence rule: weight of how far the box bottom floats above the local ground (m)",
    "w_through": "evidence rule: weight of the rays through the box core returning from beyond it, as a share of "
    "the returns a car there would give",
    "w_cover": "evidence rule: weight of the share of the box's unhidden azimuth columns holding a return (with "
    "prior columns at a car's value)",
    "w_score": "evidence rule: weight of the detector score as a logit (after score_mapping)",
    "w_mismatch": "evidence rule: weight of the shape-mismatch score (0 unless calibrated with a car-constrained "
    "backend)",
    **{f"w_{t}": f"evidence rule: weight of {text}" for t, text in PROFILE_TERM_DOCS.items()},
    "mismatch_mean": "evidence rule: the value a missing shape-mismatch term takes (a detection not completed: past "
                     "max_instances, under min_points): its mean over the calibration detections, the term "
                     "marginalised to first order (pcc calibrate-filter)",
    "reject_threshold": "evidence rule: detections whose probability of being false exceeds this are rejected "
                        "(with sensor_thresholds: where the beam model matches none of its presets)",
    "sensor_thresholds": "evidence rule: per beam-layout reject_threshold, 'preset:threshold' entries separated by "
                         "commas (e.g. 'hdl64:0.53, vlp16:0.46'; pcc calibrate-filter --sensor-thresholds): the entry "
                         "of the preset the beam model matches (sensor: auto) or names; '' = reject_threshold always",
    "trees": "evidence rule: boosted trees added to the weighted sum's logit: 'shipped' (pcc_ros/weights/"
             "filter_trees.json, boosted from the default weights), a trees file of pcc calibrate-filter --trees-out, "
             "or '' (the weighted sum alone); a file belongs to the weights it was boosted from",
    "sensor": "evidence rule: LiDAR beam model for the expected returns: auto (estimated from the scans, from the "
              "ring field when there is one; docs/filter.md) or a preset (hdl64 = KITTI, hdl32 = nuScenes, vlp16, "
              "vlp32c, vlp32c_x2, os1_64, os1_128, pandar64)",
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
    "tf_timeout": "seconds a frame waits for a transform it needs (tf lagging); then it is dropped and counted "
                  "(0: dropped at once)",
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
    "track_max_age": (0.01, 60.0),
    "track_gate": (0.01, 50.0),
    "match_threshold": (0.0, 1.0),
    "detection_threshold": (0.0, 1.0),
    "reject_threshold": (1e-6, 1.0 - 1e-6),
    "mismatch_mean": (0.0, 1.0),
    "mcd_scale": (1e-6, 10.0),
    "contour_scale": (1e-6, 10.0),
    "grid_cells": (2, 256),
    "grid_extent": (0.1, 5.0),
    "sync_slop": (0.0, 10.0),
    "queue_size": (1, 1000),
    "scan_timeout": (0.01, 3600.0),
    "tf_timeout": (0.0, 10.0),
    "qos.points.depth": (1, 1000),
    "qos.detections.depth": (1, 1000),
    "qos.outputs.depth": (1, 1000),
}

#: Parameters restricted to a fixed set of strings.
CHOICES: dict[str, tuple[str, ...]] = {
    "score_mapping": SCORE_MAPPINGS,
    "rule": RULES,
    "sensor": (AUTO, *SENSOR_PRESETS),
    "qos.points.reliability": RELIABILITIES,
    "qos.detections.reliability": RELIABILITIES,
    "qos.outputs.reliability": RELIABILITIES,
}
