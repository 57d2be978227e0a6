"""The per-frame pipeline: scan + detections in, completions and filter decisions out.

One class serves every runtime — the rclpy nodes, ``pcc replay`` and
the demo — and knows nothing of rclpy: the nodes only feed it frames and publish what
it returns, so offline results are exactly what a running node would publish.

Stages (each timed): decode -> crop (points in the configured classes' boxes, ground
returns removed) -> canonical frame -> complete (one batched backend call) -> back to
the scan frame -> shape-mismatch score -> keep / reject -> encode.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from pcc_ros.errors import MessageError
from pcc_ros.geometry.boxes import BoxCandidates, canonical_crops
from pcc_ros.geometry.boxes import warm_up as warm_up_crop
from pcc_ros.geometry.canonical import from_canonical
from pcc_ros.lograte import worth_logging
from pcc_ros.models.base import SceneContext
from pcc_ros.models.registry import check_backend_name, get_backend, load_completer
from pcc_ros.msg.detections import (
    decode_detection_array,
    transform_detections,
)
from pcc_ros.msg.pointcloud2 import RING_FIELD, point_field_names, read_xyz
from pcc_ros.msg.stamps import stamp_to_ns
from pcc_ros.msg.tf_buffer import same_frame
from pcc_ros.pipeline.beam_model import CALIBRATION_HEIGHT, BeamModel
from pcc_ros.pipeline.config import PipelineConfig
from pcc_ros.pipeline.evidence import warm_up
from pcc_ros.pipeline.filter import (
    false_probability,
    filter_terms,
    map_scores,
    mismatch_scores,
    parse_sensor_thresholds,
    reject_mask,
)
from pcc_ros.pipeline.track_memory import TrackMemory
from pcc_ros.types import Boxes, class_mask

log = logging.getLogger(__name__)

#: The filter's scan evidence is measured for every box of a configured class (max_instances
#: bounds the completion only) while their crop work bounds sum to at most this many times
#: ``max_crop_work``; past it the lowest-score boxes pass unjudged, marked and counted.
EVIDENCE_WORK_FACTOR = 10

#: An organized cloud of at most this many rows is read as one row per beam (Ouster's layout).
MAX_ORGANIZED_RINGS = 256

#: ``instance`` value of raw scan points in the completed cloud (``include_input_points``;
#: the cloud's layout is :data:`pcc_ros.pipeline.outputs.COMPLETED_CLOUD_DTYPE`).
RAW_POINT_INSTANCE = -1
#: ``source`` values of the completed cloud.
SOURCE_OBSERVED, SOURCE_COMPLETED = 0, 1
@dataclass
class FrameResult:
    """Everything one frame produces, in the scan's frame ``frame_id``.

    Per-detection arrays have one row per input detection (after invalid boxes were
    dropped, see ``skipped``): ``status`` is ``"kept"`` or ``"rejected"`` (judged),
    ``"unjudged"`` (a configured class the filter could not judge: a scan without a finite
    point, the trapcc rule without a completion; published as kept, with the
    ``pcc_filter_unjudged`` marker) or ``"skipped"`` (another class: passes untouched);
    ``mismatch`` is NaN where no shape was completed. ``skipped`` counts per reason what the
    completion left out (another class, too few points, past ``max_instances`` or the work
    bound); the evidence rule judges every detection of a configured class all the same.
    ``unjudged_originals``: the detection messages whose box failed the checks (NaN pose,
    non-positive size, the limits), republished with the marker.
    """

    stamp_ns: int
    frame_id: str
    detections: Boxes
    completed_points: np.ndarray  # (M, 3) float32, scan frame
    completed_instance: np.ndarray  # (M,) int32: detection index, RAW_POINT_INSTANCE for raw points
    crops: list[np.ndarray]  # canonical crops of the completed detections
    completions: list[np.ndarray]  # canonical completions, same order
    completed_index: np.ndarray  # detection index of each completion
    num_points: np.ndarray  # (N,) points inside each detection box
    mismatch: np.ndarray  # (N,)
    status: np.ndarray  # (N,) object
    timings_ms: dict[str, float] = field(default_factory=dict)
    skipped: dict[str, int] = field(default_factory=dict)
    #: (M,) uint8 per completed-cloud point: SOURCE_COMPLETED or SOURCE_OBSERVED (None: all completed)
    completed_source: np.ndarray | None = None
    #: (N,) detection scores after ``score_mapping`` and the threshold each was held to (None: not judged)
    probability: np.ndarray | None = None
    threshold: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.completed_source is None:
            self.completed_source = np.full(len(self.completed_points), SOURCE_COMPLETED, dtype=np.uint8)

    def completion_points(self, index: int) -> np.ndarray:
        """The points the backend made for detection ``index`` (observed points excluded)."""
        mine = (self.completed_instance == index) & (self.completed_source == SOURCE_COMPLETED)
        return self.completed_points[mine]
    #: evidence rule: probability that each detection is false (NaN: not judged) and the
    #: terms behind it (``pcc_ros.pipeline.filter.TERMS`` plus raw counts), one value per detection.
    filter_score: np.ndarray | None = None
    filter_terms: dict[str, np.ndarray] = field(default_factory=dict)
    unjudged_originals: list = field(default_factory=list)

    @property
    def keep(self) -> np.ndarray:
        return self.status != "rejected"

    @property
    def kept(self) -> Boxes:
        return self.detections[self.keep]

    @property
    def rejected(self) -> Boxes:
        return self.detections[~self.keep]


def needs_completion(config: PipelineConfig, completes: bool = True, filters: bool = True) -> bool:
    """Whether a pipeline that publishes completions (``completes``) and / or filter decisions
    (``filters``) runs the completion network: for its completions, or for a filter rule that
    scores the shape (TraPCC, or a nonzero ``w_mismatch``)."""
    return completes or (filters and config.filter.uses_mismatch)


class Pipeline:
    """Completion and shape-mismatch filtering of one frame at a time.

    Args:
        config: the parameters.
        completer: a ready backend; by default loaded from ``config.backend`` /
            ``config.checkpoint`` (the shipped default checkpoint when empty).
        completes: run the completion stage. ``False`` (a filter node whose rule gives the shape
            no weight): no backend is loaded (``completer`` is None) and no network runs; a
            rule that scores the shape completes whatever this says (:func:`needs_completion`).
        filters: run the filter stage (``False``: a completion node; no detection is judged).
    """

    def __init__(self, config: PipelineConfig, completer=None, completes: bool = True, filters: bool = True) -> None:
        self.config = config
        self.filters = filters
        self.completes = needs_completion(config, completes, filters)
        #: frames so far whose scan had no finite point / scores outside [0, 1] (each logged at 1, 101, ...)
        self.empty_scans = 0
        self.scores_outside_unit = 0
        self.crop_work_frames = 0  # frames whose boxes exceeded max_crop_work
        if completer is None and self.completes:
            completer = load_completer(
                config.backend, config.checkpoint or None, device=config.device, **self._runtime_options(config)
            )
        self.completer = completer if self.completes else None
        if not self.completes:
            check_backend_name(config.backend)  # not loaded, but a misspelt name is still refused
        warm_up_crop()  # the crop's compiled scan pass, before the first frame
        if filters and config.filter.rule == "evidence":
            warm_up()  # the filter's compiled kernels, before the first frame
        #: the filter's beam model: a preset, or estimated from the scans (sensor: auto)
        self.beam_model = BeamModel(config.filter.sensor)
        # The filter's own completion backend for its shape-mismatch term (a car-constrained
        # one such as TraPCC or AML); "" or the pipeline's backend: reuse its completions.
        self.filter_completer = None
        name = config.filter.filter_backend
        if filters and config.filter.uses_mismatch and name and name != config.backend:
            self.filter_completer = load_completer(name, None, device=config.device)
        #: the (preset, reject threshold) last in force, logged when it changes (reject_threshold)
        self.threshold_in_force: tuple[str | None, float] | None = None
        #: whether the sensor's height was last read off the presets' (warned once per time it goes off,
        #: so a height read off only at a later estimate is warned about too)
        self._off_height = False
        #: measure every filter term (the evaluation and calibration tools); False: the weighted ones
        self.all_terms = False
        #: each car's recent crops in its box frame (track_memory; None: every frame alone)
        self.track_memory = TrackMemory(config.track_max_age, config.track_gate) if config.track_memory else None

    def reject_threshold(self) -> float:
        """The evidence rule's reject threshold for the beam model in force: the ``sensor_thresholds``
        entry of the preset it matches (or names), else ``reject_threshold`` (an unknown sensor,
        or before the first estimate). Logged once, and again when it changes."""
        preset = self.beam_model.preset
        threshold = self.config.filter.threshold_for(preset)
        table = parse_sensor_thresholds(self.config.filter.sensor_thresholds)
        off = preset in table and self.beam_model.off_height()
        if off and not self._off_height:
            log.warning("filter: the sensor sits %.2f m above the ground; the %s entry of sensor_thresholds was "
                        "set for one %.2f m high and loses more cars on such a mount: set a threshold for it with "
                        "pcc calibrate-filter --sensor-from <a bag of its scans> (docs/filter.md)",
                        self.beam_model.mount_height, preset, CALIBRATION_HEIGHT)
        self._off_height = off
        if (preset, threshold) != self.threshold_in_force:
            self.threshold_in_force = (preset, threshold)
            if preset in table:
                source = f"the {preset} entry of sensor_thresholds"
            elif not table:
                source = "reject_threshold (no sensor_thresholds given)"
            elif self.beam_model.model is None:
                source = "reject_threshold until the first beam estimate"
            elif preset is None:
                source = ("reject_threshold: the beam model matches no preset (a threshold set for this sensor: "
                          "pcc calibrate-filter --sensor-from <a bag of its scans>)")
            else:
                source = f"reject_threshold: sensor_thresholds has no entry for {preset}"
            log.info("filter: reject threshold %.4f, %s", threshold, source)
        return threshold

    @staticmethod
    def _runtime_options(config: PipelineConfig) -> dict[str, Any]:
        if not get_backend(config.backend).learned:
            return {}  # baselines have no network: batch size, precision and workers do not apply
        return {"batch_size": config.batch_size, "half_precision": config.half_precision, "workers": config.workers,
                "decode_density": config.decode_density}

    # ------------------------------------------------------------------ core

    def process(self, points: np.ndarray, detections: Boxes, stamp_ns: int = 0, frame_id: str = "",
                rings: np.ndarray | None = None) -> FrameResult:
        """Run one frame. ``points``: ``(N, >=3)`` finite scan points; ``detections``: valid boxes;
        ``rings``: the scan's ring field (one value per point) when it has one, read by the beam
        model's estimate (``sensor: auto``; :meth:`BeamModel.due` says when it is wanted)."""
        cfg = self.config
        timings: dict[str, float] = {}
        n = len(detections)
        status = np.full(n, "skipped", dtype=object)
        mismatch = np.full(n, np.nan)
        num_points = np.zeros(n, dtype=np.int64)
        skipped: dict[str, int] = {}

        tic = time.perf_counter()
        wanted = class_mask(detections.label, cfg.classes)  # other classes pass the filter untouched
        _count(skipped, "other class", int((~wanted).sum()))
        candidates = np.flatnonzero(wanted)
        dropped = candidates[:0]
        if len(candidates) > cfg.max_instances:
            order = np.argsort(-detections.score[candidates], kind="stable")
            dropped = candidates[order[cfg.max_instances :]]
            _count(skipped, "over max_instances", len(dropped))
            candidates = np.sort(candidates[order[: cfg.max_instances]])
        # Work bound: crop, completion and filter cost grows with the (point, box) pairs, about
        # the points under each box's footprint. Counted before any pair is formed; beyond
        # max_crop_work the lowest-score boxes are skipped (counted), so one hostile frame
        # (hundreds of huge boxes over a dense scan) cannot stall a node or exhaust memory.
        crop_index, canonical, fits, work = _bounded_crop(points, detections[candidates], cfg)
        box_work = np.zeros(n)  # the (point, box) work bound of every box of a configured class
        box_work[candidates] = work
        if fits is not None:
            _count(skipped, "over max_crop_work", int((~fits).sum()))
            self.crop_work_frames += 1  # a dense sensor on a busy street can meet it every frame: not every line
            if worth_logging(self.crop_work_frames, every=100):
                log.warning("frame %d: about %d point-box pairs in %d boxes exceed max_crop_work %d; skipped the %d "
                            "lowest-score boxes (%d such frames so far)", stamp_ns, int(work.sum()), len(candidates),
                            cfg.max_crop_work, int((~fits).sum()), self.crop_work_frames)
            candidates = candidates[fits]
        counts = np.array([len(c) for c in canonical], dtype=np.int64)
        num_points[candidates] = counts
        timings["crop_ms"] = _ms(tic)

        enough = counts >= cfg.min_points
        empty = counts == 0
        _count(skipped, "too few points", int((~enough & ~empty).sum()))
        # A box with no return at all holds no vehicle evidence: maximal mismatch, so the
        # score gate alone decides (a confident detection of an occluded car survives).
        mismatch[candidates[empty]] = 1.0

        tic = time.perf_counter()
        selected = candidates[enough]
        crops = [canonical[i] for i in np.flatnonzero(enough)]
        context = None
        if getattr(self.completer, "uses_context", False) and crops:
            context = SceneContext.from_frame(detections[selected], crops)
        sizes = detections.size[selected]
        completions = []
        if self.completes:
            inputs = crops
            if self.track_memory is not None:  # the car's accumulated crops (causal); the filter reads this frame's
                inputs = self.track_memory.update(detections[selected], crops, stamp_ns)
                timings["track_memory_ms"] = _ms(tic)
            completions = self.completer.complete(inputs, context, sizes=sizes) if crops else []
            timings["complete_ms"] = _ms(tic)
        else:  # nothing completed: no crop stands for a completion (crops, completions, completed_index agree)
            crops, selected = [], selected[:0]

        tic = time.perf_counter()
        filter_score = np.full(n, np.nan)
        terms: dict[str, np.ndarray] = {}
        threshold = cfg.detection_thresholds(detections.label)
        if self.filters:
            if crops and cfg.filter.uses_mismatch:
                shapes = completions
                if self.filter_completer is not None:
                    shapes = self.filter_completer.complete(crops, context, sizes=sizes)
                mismatch[selected] = mismatch_scores(crops, shapes, cfg.filter)
            if cfg.filter.rule == "evidence":
                # Every detection of a configured class is judged, sparse or not (min_points does not
                # apply), completed or not: max_instances and the work bound limit the completion,
                # not the scan evidence; a missing shape term is marginalised (filter.term_matrix).
                judged_idx = np.flatnonzero(wanted)
                if not len(points) and len(judged_idx):  # no finite return at all: no evidence either way
                    status[judged_idx] = "unjudged"
                    self._empty_scan(stamp_ns, skipped, len(judged_idx))
                    judged_idx = judged_idx[:0]
                judged_idx = self._evidence_budget(points, detections, judged_idx, dropped, box_work, status, skipped,
                                                   stamp_ns)
                sensor = self.beam_model.for_frame(points, rings)
                if len(judged_idx):
                    part = filter_terms(points, detections[judged_idx], cfg.filter, mismatch[judged_idx],
                                        workers=filter_threads(cfg), sensor=sensor,
                                        weighted_only=not self.all_terms)
                    terms = {k: np.full(n, np.nan) for k in part}
                    for k, v in part.items():
                        terms[k][judged_idx] = v
                    filter_score[judged_idx] = false_probability(part, cfg.filter)
                    reject = filter_score[judged_idx] > self.reject_threshold()
                    status[judged_idx] = np.where(reject, "rejected", "kept")
            else:
                judged = np.isfinite(mismatch) & bool(len(points))
                if not len(points) and len(candidates):
                    self._empty_scan(stamp_ns, skipped, len(candidates))
                status[wanted & ~judged] = "unjudged"  # no completion to compare: kept, marked
                rejected = np.zeros(n, dtype=bool)
                for value in np.unique(threshold):  # one pass per distinct class threshold (a handful)
                    group = threshold == value
                    rejected[group] = reject_mask(
                        mismatch[group], detections.score[group], replace(cfg.filter, detection_threshold=float(value))
                    )
                status[judged] = np.where(rejected[judged], "rejected", "kept")
            timings["filter_ms"] = _ms(tic)
        probability = map_scores(detections.score, cfg.filter.score_mapping)

        tic = time.perf_counter()
        sensor = [
            from_canonical(c, detections.center[i], detections.yaw[i], detections.size[i, 0])
            for c, i in zip(completions, selected)
        ]
        parts = [s.astype(np.float32) for s in sensor]
        instance = [np.full(len(s), i, dtype=np.int32) for s, i in zip(sensor, selected)]
        source = [np.full(len(s), SOURCE_COMPLETED, dtype=np.uint8) for s in sensor]
        observed = np.zeros(len(points), dtype=bool)  # raw points already published with their instance
        if cfg.include_observed_points and len(selected):
            chosen = [crop_index[k] for k in np.flatnonzero(enough)]
            index = np.concatenate(chosen)
            observed[index] = True
            parts.append(np.ascontiguousarray(points[index, :3], dtype=np.float32))
            instance.append(np.repeat(selected.astype(np.int32), [len(c) for c in chosen]))
            source.append(np.full(len(index), SOURCE_OBSERVED, dtype=np.uint8))
        if cfg.include_input_points:
            raw = np.flatnonzero(~observed)
            parts.insert(0, np.ascontiguousarray(points[raw, :3], dtype=np.float32))
            instance.insert(0, np.full(len(raw), RAW_POINT_INSTANCE, dtype=np.int32))
            source.insert(0, np.full(len(raw), SOURCE_OBSERVED, dtype=np.uint8))
        completed = np.concatenate(parts) if parts else np.zeros((0, 3), np.float32)
        instance_ids = np.concatenate(instance) if instance else np.zeros(0, np.int32)
        sources = np.concatenate(source) if source else np.zeros(0, np.uint8)
        timings["uncanonical_ms"] = _ms(tic)

        return FrameResult(
            stamp_ns=int(stamp_ns),
            frame_id=frame_id,
            detections=detections,
            completed_points=completed,
            completed_instance=instance_ids,
            crops=crops,
            completions=completions,
            completed_index=selected,
            num_points=num_points,
            mismatch=mismatch,
            status=status,
            timings_ms=timings,
            skipped=skipped,
            completed_source=sources,
            probability=probability,
            threshold=threshold,
            filter_score=filter_score,
            filter_terms=terms,
        )

    # ------------------------------------------------------------------ messages

    def _evidence_budget(self, points, detections: Boxes, judged_idx, dropped, box_work, status, skipped,
                         stamp_ns: int) -> np.ndarray:
        """The boxes the evidence measures: all of ``judged_idx`` unless their work bounds (the
        crop's, measured for the boxes past max_instances too) sum past
        :data:`EVIDENCE_WORK_FACTOR` x ``max_crop_work``; then the highest-scoring that fit, the
        rest marked unjudged (counted, logged): a hostile frame of huge boxes stays bounded."""
        cfg = self.config
        if len(dropped) and len(points):
            box_work[dropped] = BoxCandidates(points, detections[dropped], cfg.box_margin,
                                              cfg.ground_margin).pairs_per_box
        fits = crop_budget(box_work[judged_idx], detections[judged_idx], EVIDENCE_WORK_FACTOR * cfg.max_crop_work)
        if fits is None:
            return judged_idx
        over = judged_idx[~fits]
        status[over] = "unjudged"
        _count(skipped, "unjudged over evidence work", len(over))
        log.warning("frame %d: about %d point-box pairs in %d boxes exceed %d x max_crop_work; the %d lowest-score "
                    "boxes pass unjudged (marked)", stamp_ns, int(box_work[judged_idx].sum()), len(judged_idx),
                    EVIDENCE_WORK_FACTOR, len(over))
        return judged_idx[fits]

    def _empty_scan(self, stamp_ns: int, skipped: dict[str, int], n: int) -> None:
        """A scan without a finite point (a driver starting up, a blocked sensor, an organized
        cloud all NaN) says nothing about the boxes: they pass the filter unjudged (counted as
        "empty scan"; logged for the first such frame and every 100th) instead of all being
        rejected for holding no returns."""
        _count(skipped, "empty scan", n)
        self.empty_scans += 1
        if worth_logging(self.empty_scans, every=100):
            log.warning("frame %d: the scan has no finite point; its %d detections pass the filter unjudged "
                        "(%d such frames so far)", stamp_ns, n, self.empty_scans)

    def _check_score_range(self, boxes: Boxes) -> None:
        """``score_mapping: identity`` means probabilities: scores outside [0, 1] (logits?) are
        kept as they are but never silently — the first frame and then every 100th is logged."""
        if self.config.filter.score_mapping != "identity" or not len(boxes):
            return
        outside = int(((boxes.score < 0.0) | (boxes.score > 1.0)).sum())
        if outside:
            self.scores_outside_unit += 1
            if worth_logging(self.scores_outside_unit, every=100):
                log.warning("%d detection scores outside [0, 1] (e.g. %.3g) with score_mapping identity (%d frames so "
                            "far): the detector gives logits? set score_mapping: sigmoid",
                            outside, float(boxes.score[(boxes.score < 0) | (boxes.score > 1)][0]),
                            self.scores_outside_unit)

    def _read_scan(self, cloud_msg) -> tuple[np.ndarray, np.ndarray | None]:
        """The scan's finite points and, on a frame the beam model estimates from, each point's
        ring: the ``ring`` field (Velodyne, Ouster, Hesai drivers), else the row of an organized
        cloud (one row per beam); None otherwise."""
        if self.config.filter.rule != "evidence" or not self.beam_model.due():
            return read_xyz(cloud_msg), None
        if RING_FIELD in point_field_names(cloud_msg):
            both = read_xyz(cloud_msg, (RING_FIELD,))
            return np.ascontiguousarray(both[:, :3]), both[:, 3]
        points = read_xyz(cloud_msg)
        height = int(cloud_msg.height)
        if 1 < height <= MAX_ORGANIZED_RINGS:
            every = read_xyz(cloud_msg, skip_nonfinite=False)
            finite = np.isfinite(every).all(axis=1)
            return points, np.repeat(np.arange(height, dtype=np.float32), int(cloud_msg.width))[finite]
        return points, None

    def process_messages(
        self, cloud_msg, detections_msg, transform=None, with_originals: bool = True
    ) -> tuple[FrameResult, list | None]:
        """Decode a PointCloud2 and a Detection3DArray (any message classes) and run the frame.

        Invalid detections (NaN pose, non-positive size) are dropped with a warning and
        counted in ``skipped``; a malformed cloud or array raises
        :class:`pcc_ros.errors.MessageError` for the caller to log and skip. Detections in
        another frame than the scan need ``transform`` (a
        :class:`~pcc_ros.geometry.transforms.Transform`, ``scan frame <- detections' frame``,
        as the node core looks it up): the decoded boxes are moved once, and the republished
        detection messages are moved with them; without it such a frame is a ``MessageError``.
        Returns the result and the valid subset of ``detections_msg.detections``, in the
        order of ``result.detections`` (so the outputs republish the original messages);
        ``with_originals=False`` (a caller that republishes no detection message): ``None``,
        and no message is copied or moved.
        """
        for what, msg in (("scan", cloud_msg), ("detections", detections_msg)):
            if stamp_to_ns(msg.header.stamp) < 0:
                raise MessageError(f"{what} stamp {stamp_to_ns(msg.header.stamp)} ns is negative (before 1970)")
        cloud_frame, boxes_frame = str(cloud_msg.header.frame_id), str(detections_msg.header.frame_id)
        if boxes_frame and not same_frame(boxes_frame, cloud_frame) and transform is None:
            raise MessageError(
                f"detections are in frame '{boxes_frame}' but the scan is in '{cloud_frame}': "
                "transform them first (the nodes do it with tf2)"
            )
        tic = time.perf_counter()
        points, rings = self._read_scan(cloud_msg)
        boxes, valid = decode_detection_array(
            detections_msg, skip_invalid=True, limits=self.config.detection_limits(), transform=transform
        )
        if self.config.class_map:  # detector ids -> names, before classes / class_thresholds match
            boxes = replace(boxes, label=self.config.map_labels(boxes.label))
        self._check_score_range(boxes)
        originals, invalid = None, []
        if with_originals:
            originals = [d for d, ok in zip(detections_msg.detections, valid) if ok]
            invalid = [d for d, ok in zip(detections_msg.detections, valid) if not ok]
            if transform is not None:
                originals = transform_detections(originals, transform, cloud_frame)
                invalid = transform_detections(invalid, transform, cloud_frame)
        decode_ms = _ms(tic)
        result = self.process(
            points, boxes, stamp_to_ns(cloud_msg.header.stamp), str(cloud_msg.header.frame_id), rings
        )
        result.timings_ms = {"decode_ms": decode_ms, **result.timings_ms}
        result.unjudged_originals = invalid
        _count(result.skipped, "invalid detection", int((~valid).sum()))
        return result, originals


def crop_budget(work: np.ndarray, boxes: Boxes, max_work: int) -> np.ndarray | None:
    """Which boxes the crop stage takes when their work bounds ``work`` sum past ``max_work``:
    the highest-scoring ones whose running total stays within it (``None``: all of them)."""
    if work.sum() <= max_work:
        return None
    order = np.argsort(-boxes.score, kind="stable")
    fits = np.zeros(len(boxes), dtype=bool)
    fits[order] = np.cumsum(work[order]) <= max_work
    return fits


def filter_threads(cfg: PipelineConfig) -> int:
    """CPU threads of the filter's measurements: as many as the completion had -- ``workers``,
    or torch's intra-op threads when ``workers`` is 1 (the completion then runs on those)."""
    if cfg.workers > 1:
        return cfg.workers
    import torch  # the completion's runtime (loaded with the backends)

    return max(1, torch.get_num_threads())


def _bounded_crop(points: np.ndarray, boxes: Boxes, cfg: PipelineConfig):
    """The crop stage: ``(indices, canonical, fits, work)`` -- the crops of the boxes within
    ``max_crop_work`` (``fits``: which boxes, ``None`` when all fit; ``work``: the bound per box).

    One :class:`~pcc_ros.geometry.boxes.BoxCandidates` pass gives the work bound (its
    ``pairs_per_box``, known before any pair is formed) and then the crops of the boxes that
    fit. (``benchmarks/_reference.py`` swaps this function for the previous crop, the baseline of
    ``pcc bench crop`` and ``pcc bench pipeline``.)"""
    candidates = BoxCandidates(points, boxes, cfg.box_margin, cfg.ground_margin)
    work = candidates.pairs_per_box
    fits = crop_budget(work, boxes, cfg.max_crop_work)
    indices, canonical = canonical_crops(candidates, fits)
    if fits is not None:
        kept = np.flatnonzero(fits).tolist()
        indices, canonical = [indices[i] for i in kept], [canonical[i] for i in kept]
    return indices, canonical, fits, work


def _count(counter: dict[str, int], reason: str, n: int) -> None:
    if n:
        counter[reason] = counter.get(reason, 0) + n


def _ms(tic: float) -> float:
    return (time.perf_counter() - tic) * 1e3

