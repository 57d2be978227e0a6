"""``pcc eval --real``: completion quality on real, labelled LiDAR sequences.

There is no complete shape of a real car, so each track's crops over the whole sequence,
motion-compensated by their boxes into the canonical frame
(:mod:`pcc_ros.data.track_aggregate`), form its multi-view *partial* ground truth. Every
observation of a track with at least ``--min-track-frames`` observations is completed by
every backend and scored with :mod:`pcc_ros.metrics.realdata` (completeness, fidelity,
side-view CD, share inside the box, vertical extent against the box, front-view balance,
output points), overall and by distance and input point-count band. An ``aggregated GT``
row scores the reference itself on the box metrics, the yardstick for the backends; a
``NAME+input`` row scores each learned backend's completion together with the input crop
(what ``completion_node`` publishes with ``include_input_points: true``).

The reference contains the evaluated frame's own crop (as in the AML / TraPCC KITTI
protocol); the real frames used in training (``pcc train --real``) are other recordings
(KITTI object, nuScenes), so these tracks stay held out. Single-frame datasets (nuScenes
key frame, KITTI object) have no multi-view reference and are reported as skipped.

Example::

    pcc eval --real --json out/real.json --plot out/real.png
"""

from __future__ import annotations

import logging
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from pcc_ros.data.layouts import download_hint
from pcc_ros.data.sources import open_frames
from pcc_ros.data.track_aggregate import collect_tracks
from pcc_ros.errors import BackendError, CheckpointError, ConfigError, DataError
from pcc_ros.geometry.boxes import crop_canonical, iou_3d
from pcc_ros.geometry.canonical import from_canonical, to_canonical
from pcc_ros.metrics.balance import track_consistency
from pcc_ros.metrics.realdata import REAL_METRICS, draw_three_views, mean_rows, real_instance_metrics
from pcc_ros.models import available, backend_names, get_backend, load_completer
from pcc_ros.models.base import SceneContext
from pcc_ros.pipeline.core import PipelineConfig
from pcc_ros.pipeline.track_memory import TrackMemory
from pcc_ros.tables import metric_cell, print_table
from pcc_ros.types import Boxes, class_mask
from pcc_ros.workflows.evaluate import DISTANCE_BANDS, POINT_BANDS, write_results

log = logging.getLogger("pcc.eval.real")

#: Tables printed, in order (``spacing`` is printed with fidelity for comparison).
TABLE_METRICS = ("completeness", "far_completeness", "completeness_sym", "far_completeness_sym", "fidelity",
                 "fidelity_generated", "side_cd", "inside_box",
                 "bottom_gap", "top_gap", "lateral_offset", "consistency", "points")
REFERENCE_ROW = "aggregated GT"


def node_crop() -> tuple[float, float, int]:
    """``(box_margin, ground_margin, min_points)`` of ``completion_node`` (the pipeline defaults):
    inputs are cropped as the node crops them, so the scored union is what it publishes."""
    cfg = PipelineConfig()
    return float(cfg.box_margin), float(cfg.ground_margin), int(cfg.min_points)


def node_decode_density() -> int:
    """``completion_node``'s default ``decode_density`` (what the learned rows are decoded with)."""
    return int(PipelineConfig().decode_density)


def real_instances(
    sources: list[Path], min_track_frames: int = 2, min_points: int | None = None, voxel_m: float = 0.03,
    classes: tuple[str, ...] = ("Car", "Van"), boxes: str = "ground_truth", detections_dir: Path | None = None,
    match_iou: float = 0.5, matched_labels: bool = False, mirror: bool = False,
) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """Evaluation instances of the labelled real ``sources`` and a report of what was skipped.

    The reference of a track is the voxel-thinned aggregate of its *labelled* boxes' tight crops
    (no margin, the lowest 0.1 m dropped as ground). The inputs are cropped as
    ``completion_node`` crops (its ``box_margin`` / ``ground_margin``; fewer than its
    ``min_points`` points: not completed, skipped) from ``boxes``:

    * ``ground_truth``: the labelled boxes;
    * ``detections``: the detector's boxes (``detections_dir`` for KITTI, a bag's own). Each is
      matched to the labelled box of its frame with the highest 3D IoU (>= ``match_iou``); its
      crop, completion and box metrics are in the *detection's* canonical frame, and the track's
      reference is moved there (through the sensor frame, with the matched label's box).
      Unmatched detections (false positives) have no reference and are counted as skipped.
      ``matched_labels``: crop each matched detection's *labelled* box instead (the same
      observations as the detector rows, with the labels' boxes; the frame's scene context is then
      the matched labels): what the detector's box errors cost, apart from which cars it finds.

    ``mirror``: every frame reflected across the sensor's x-z plane first (:meth:`Sample.mirrored`):
    the same cars seen from their other flank.

    Each instance: ``key``, ``partial`` (canonical), ``reference`` (canonical, same frame),
    ``size`` (box l, w, h), ``distance``, ``track_frames``, ``label``, ``frame_key``, ``center``, ``yaw``,
    ``origin`` (the sensor in the canonical frame: which half is unseen), ``track`` and ``frame``
    (the consecutive completions of a track are compared for consistency).
    """
    if boxes not in ("ground_truth", "detections"):
        raise ConfigError(f"real-data boxes must be ground_truth or detections, got {boxes!r}")
    if matched_labels and boxes != "detections":
        raise ConfigError("--real-matched-labels needs --real-detections (the detections pick the observations)")
    margin, ground_margin, node_min = node_crop()
    min_points = node_min if min_points is None else int(min_points)
    instances: list[dict[str, Any]] = []
    report: dict[str, Any] = {}
    for source in sources:
        if not source.exists():
            raise DataError(f"{source}: real dataset not found (pass --real-sources: KITTI tracking / object, "
                            "nuScenes or Argoverse 2 roots)", hint=download_hint())
        skipped: Counter = Counter()
        frames = list(open_frames(source, detections_dir=detections_dir) if detections_dir else open_frames(source))
        frames = [frame.mirrored() for frame in frames] if mirror else frames
        tracks = collect_tracks(frames, classes=classes, skipped=skipped)
        references = {}
        for key, track in tracks.items():  # loop over tracks; points are vectorised inside
            if len(track) < min_track_frames:
                skipped["track_too_short"] += len(track)
                continue
            references[key] = (track.aggregate(voxel_m=voxel_m), len(track))
        used = 0
        for frame in frames:  # tens of frames; the boxes of a frame are cropped at once
            gt = frame.ground_truth
            if gt is None or len(gt) == 0:
                continue
            gt = gt[class_mask(gt.label, classes)]
            gt = gt[gt.valid_mask()]
            if boxes == "ground_truth":
                chosen, match = gt, np.arange(len(gt))
            else:
                det = frame.detections
                if det is None:  # e.g. the nuScenes key frame beside KITTI detections: counted, not fatal
                    skipped["frame_without_detections"] += 1
                    continue
                det = det[class_mask(det.label, classes)]
                chosen = det[det.valid_mask()]
                if len(chosen) == 0:
                    continue
                iou = iou_3d(chosen, gt) if len(gt) else np.zeros((len(chosen), 0))
                match = iou.argmax(axis=1) if len(gt) else np.full(len(chosen), -1)
                if len(gt):
                    match[iou.max(axis=1) < match_iou] = -1
                skipped["detection_unmatched"] += int((match < 0).sum())
                if matched_labels:  # the same observations, cropped from their labelled boxes
                    chosen, match = gt[match[match >= 0]], match[match >= 0]
            if len(chosen) == 0:
                continue
            _, crops = crop_canonical(np.asarray(frame.points), chosen, margin=margin, ground_margin=ground_margin)
            # what completion_node completes in this frame (every box with enough points, scored or not:
            # unmatched detections and cars without a multi-view reference too) is the scene context
            completed = np.flatnonzero([len(c) >= max(min_points, 1) for c in crops])
            frame_scene = (chosen[completed], [np.ascontiguousarray(crops[j], dtype=np.float32) for j in completed])
            slot_of = {int(j): s for s, j in enumerate(completed)}
            for i, crop in enumerate(crops):  # boxes of one frame
                g = int(match[i])
                if g < 0:
                    continue
                key = f"{frame.sequence}/{gt.track_id[g]}"
                if key not in references:
                    skipped["no_multiview_reference"] += 1
                    continue
                if len(crop) < max(min_points, 1):
                    skipped["input_too_few_points"] += 1
                    continue
                reference, n_frames = references[key]
                if boxes == "detections" and not matched_labels:  # the label's canonical frame -> the detection's
                    sensor = from_canonical(reference, gt.center[g], float(gt.yaw[g]), float(gt.size[g, 0]))
                    reference = to_canonical(sensor, chosen.center[i], float(chosen.yaw[i]),
                                             float(chosen.size[i, 0])).astype(np.float32)
                center = np.asarray(chosen.center[i], dtype=np.float64)
                origin = to_canonical(np.zeros((1, 3)), center, float(chosen.yaw[i]), float(chosen.size[i, 0]))[0]
                suffix = "/label-of-det" if matched_labels else "/det" if boxes == "detections" else ""
                instances.append({"key": f"{source.name}:{key}@{frame.index}{suffix}",
                                  "partial": np.ascontiguousarray(crop, dtype=np.float32), "reference": reference,
                                  "size": np.asarray(chosen.size[i], dtype=np.float64),
                                  "distance": float(np.linalg.norm(center)), "track_frames": n_frames,
                                  "label": str(gt.label[g]), "frame_key": f"{source}:{frame.sequence}:{frame.index}",
                                  "center": center, "yaw": float(chosen.yaw[i]), "frame_scene": frame_scene,
                                  "scene_slot": slot_of[i], "origin": origin.astype(np.float64),
                                  "track": f"{source}:{key}{suffix}", "frame": int(frame.index)})
                used += 1
        report[str(source)] = {"tracks": len(tracks), "instances": used, "boxes": boxes, "skipped": dict(skipped)}
        if used == 0:
            log.info("%s: no usable observation with a multi-view reference (a single-frame dataset has none): "
                     "skipped %s", source, dict(skipped))
        elif skipped:
            log.info("%s: %d instances; skipped %s", source, used, dict(skipped))
    return instances, report


def _bands(instances: list[dict[str, Any]], rows: list[dict[str, float]]) -> dict[str, Any]:
    distance = np.array([i["distance"] for i in instances])
    points = np.array([len(i["partial"]) for i in instances])
    return {
        "overall": mean_rows(rows, np.ones(len(instances), bool)),
        "by_distance": {b: mean_rows(rows, (distance >= lo) & (distance < hi)) for b, lo, hi in DISTANCE_BANDS},
        "by_points": {b: mean_rows(rows, (points >= lo) & (points < hi)) for b, lo, hi in POINT_BANDS},
    }


def scene_contexts(instances: list[dict[str, Any]]) -> list[Any]:
    """One :class:`~pcc_ros.models.base.SceneContext` per instance, what the pipeline gives a
    context-using backend: every other box the node completes in the same frame is a neighbour.

    Instances from :func:`real_instances` carry their frame's completed boxes and crops
    (``frame_scene``, including unmatched detections and cars without a multi-view reference)
    and their ``scene_slot`` in it; without them the other evaluated cars of the frame are used."""
    contexts: list[Any] = [None] * len(instances)
    groups: dict[str, list[int]] = {}
    for i, inst in enumerate(instances):
        groups.setdefault(inst["frame_key"], []).append(i)
    for members in groups.values():  # loop over frames; a handful of cars each
        scene = instances[members[0]].get("frame_scene")
        if scene is not None:
            frame_contexts = SceneContext.from_frame(*scene)
            for i in members:
                contexts[i] = frame_contexts[instances[i]["scene_slot"]]
            continue
        boxes = Boxes(np.stack([instances[i]["center"] for i in members]),
                      np.stack([instances[i]["size"] for i in members]),
                      np.array([instances[i]["yaw"] for i in members]),
                      np.array([instances[i]["label"] for i in members], dtype=object))
        for i, ctx in zip(members, SceneContext.from_frame(boxes, [instances[i]["partial"] for i in members])):
            contexts[i] = ctx
    return contexts


#: Suffix of the rows that score only the points a learned backend generated (its own shape).
GENERATED_SUFFIX = "/generated"


def evaluate_real(
    instances: list[dict[str, Any]], backends: list[str], checkpoints: dict[str, Path], device: str = "cpu",
    batch_size: int = 32, progress: bool = True, keep_input: bool = True, decode_density: int | None = None,
    strict: bool = False, accumulated: list[np.ndarray] | None = None,
) -> tuple[dict[str, Any], dict[str, list[np.ndarray]]]:
    """Complete every instance with every backend (batched, with the boxes' sizes) and score it.

    Row ``NAME`` of a learned backend is what ``completion_node`` publishes for each car with its
    default ``include_observed_points: true``: the partial-preserving completion
    ``Completer.complete(..., keep_input=True)`` (the observed crop plus the generated points).
    Row ``NAME/generated`` scores the generated points alone (the network's own shape, what the
    filter's mismatch term reads). ``keep_input=False`` scores only the generated points, as
    ``NAME``. Backends that read scene context (TraPCC) get the other evaluated cars of the
    frame as neighbours. ``decode_density``: the learned backends' (default: the node's).
    A backend that does not load (no or a damaged checkpoint) is skipped with a warning, or
    with ``strict`` (the backends and checkpoints the user named) raises. ``accumulated``: one
    cloud per instance to complete instead of its crop (track-level completion,
    :func:`track_memory_inputs`); the published rows are still this frame's crop plus the
    generated points."""
    results: dict[str, Any] = {}
    completions: dict[str, list[np.ndarray]] = {}
    partials = [i["partial"] for i in instances]
    sizes = np.stack([i["size"] for i in instances]) if instances else np.zeros((0, 3))
    ref_rows = [real_instance_metrics(i["reference"], i["partial"], i["reference"], i["size"], i.get("origin"))
                for i in instances]
    for name in backends:
        try:
            cls = get_backend(name)
            density = node_decode_density() if decode_density is None else int(decode_density)
            options = {"batch_size": batch_size, "decode_density": density} if cls.learned else {}
            completer = load_completer(name, checkpoints.get(name), device=device, **options)
        except (CheckpointError, BackendError) as exc:
            if strict or name in checkpoints:
                raise
            log.warning("%s: skipped (%s)", name, exc)
            results[name] = {"skipped": str(exc)}
            continue
        contexts = scene_contexts(instances) if getattr(completer, "uses_context", False) else None
        keep = keep_input and cls.learned
        outs: list[np.ndarray] = []
        inputs = partials if accumulated is None else accumulated
        tic = time.perf_counter()
        for start in tqdm(range(0, len(partials), 64), desc=f"complete {name}", disable=not progress, leave=False):
            chunk = None if contexts is None else contexts[start : start + 64]
            outs.extend(completer.complete(inputs[start : start + 64], chunk, sizes=sizes[start : start + 64],
                                           keep_input=keep and accumulated is None))
        seconds = time.perf_counter() - tic
        if keep and accumulated is not None:  # published: this frame's crop, then what the accumulated cloud gave
            outs = [np.concatenate([p, o]) for p, o in zip(partials, outs)]
        variants = {name: outs}
        if keep:  # the contract of keep_input: the partial first, then the generated points
            variants[name + GENERATED_SUFFIX] = [o[len(p):] for o, p in zip(outs, partials)]
        for row, clouds in variants.items():
            rows = score_rows(instances, clouds)
            results[row] = {**_bands(instances, rows), "learned": bool(cls.learned),
                            "completion_ms_per_instance": 1e3 * seconds / max(len(instances), 1)}
            if cls.learned:
                ck = getattr(completer, "checkpoint_config", None) or {}
                results[row]["checkpoint"] = str(checkpoints.get(name, "shipped default"))
                results[row]["checkpoint_sha256"] = ck.get("sha256")
                results[row]["box_aspect"] = getattr(completer, "box_aspect", None)
                results[row]["decode_density"] = getattr(completer, "decode_density", None)
                results[row]["variant"] = ("generated points only (the network's own shape)" if row != name else
                                           "published: observed crop + generated points" if keep else "generated")
            completions[row] = clouds
    results[REFERENCE_ROW] = {**_bands(instances, ref_rows), "learned": False}
    return results, completions


def track_memory_inputs(instances: list[dict[str, Any]], association: str = "ids", max_age_s: float | None = None,
                        gate_m: float | None = None, frame_period_s: float = 0.1) -> tuple[list[np.ndarray], float]:
    """Each instance's accumulated canonical cloud as ``completion_node`` with ``track_memory`` builds it
    (:class:`~pcc_ros.pipeline.track_memory.TrackMemory`, the node's ``track_max_age`` / ``track_gate``
    unless given), feeding the frames in order at ``frame_period_s`` (KITTI: 10 Hz); causal: only a
    track's earlier frames. ``association``: ``ids`` (the labels' track ids, a tracker's stable
    ``Detection3D.id``) or ``nearest`` (ids left empty: nearest box centre within the gate).
    Returns the clouds and the memory's mean cost per frame in milliseconds."""
    if association not in ("ids", "nearest"):
        raise ConfigError(f"--real-track-memory must be ids or nearest, got {association!r}")
    cfg = PipelineConfig()
    memory = TrackMemory(cfg.track_max_age if max_age_s is None else max_age_s,
                         cfg.track_gate if gate_m is None else gate_m)
    out: list[np.ndarray] = [np.zeros((0, 3), np.float32)] * len(instances)
    frames: dict[tuple[str, int], list[int]] = {}
    for i, inst in enumerate(instances):
        frames.setdefault((inst["frame_key"].rsplit(":", 1)[0], inst["frame"]), []).append(i)
    seconds, sequence = 0.0, None
    for (seq, frame), members in sorted(frames.items()):  # tens of frames, in order
        if seq != sequence:  # another recording: nothing carries over
            memory.clear()
            sequence = seq
        boxes = Boxes(np.stack([instances[i]["center"] for i in members]),
                      np.stack([instances[i]["size"] for i in members]),
                      np.array([instances[i]["yaw"] for i in members]),
                      np.array([instances[i]["label"] for i in members], dtype=object), np.ones(len(members)),
                      np.array([instances[i]["track"] if association == "ids" else "" for i in members], dtype=object))
        tic = time.perf_counter()
        clouds = memory.update(boxes, [instances[i]["partial"] for i in members], int(frame * frame_period_s * 1e9))
        seconds += time.perf_counter() - tic
        for i, cloud in zip(members, clouds):
            out[i] = cloud
    return out, 1e3 * seconds / max(len(frames), 1)


def score_rows(instances: list[dict[str, Any]], clouds: list[np.ndarray]) -> list[dict[str, float]]:
    """Per-instance real-data metrics of one row's ``clouds`` (canonical), consistency included:
    each instance against the same track's completion in the previous frame, in metres."""
    rows = [real_instance_metrics(o, i["partial"], i["reference"], i["size"], i.get("origin"))
            for o, i in zip(clouds, instances)]
    steady = track_consistency([i.get("track", "") for i in instances], [i.get("frame", 0) for i in instances],
                               clouds)
    for row, value, inst in zip(rows, steady, instances):
        row["consistency"] = float(value) * float(inst["size"][0])
    return rows


#: The bars per learned backend: completeness (published and generated-only) this far below mirror's,
#: the generated points' lateral balance at most this many metres, fidelity within this many spacings.
GAIN_BAR, BALANCE_BAR_M, FIDELITY_BAR = 0.4, 0.10, 2.0


def summary_rows(results: dict[str, Any]) -> list[dict[str, Any]]:
    """One row per backend, the README's real-data table: published completeness, and on the
    generated points alone (a learned backend's ``NAME/generated`` row; a baseline's whole output)
    completeness, its gain over mirror's, the unseen half's completeness, the lateral balance and
    the consistency between consecutive frames (metres, overall means). The two ``*_sym`` columns
    score the published completeness and the generated points' unseen half against the symmetric
    reference (the aggregate united with its left / right reflection), beside the plain ones."""
    mirror = results.get("mirror", {}).get("overall", {}).get("completeness")
    rows = []
    for name, res in results.items():
        if "overall" not in res or name == REFERENCE_ROW or name.endswith(GENERATED_SUFFIX):
            continue
        gen = results.get(name + GENERATED_SUFFIX, res)["overall"]
        rows.append({
            "backend": name, "completeness": res["overall"]["completeness"],
            "completeness_sym": res["overall"].get("completeness_sym"),
            "generated_completeness": gen["completeness"],
            "generated_gain_vs_mirror": None if not mirror else 1.0 - gen["completeness"] / mirror,
            "far_completeness": gen["far_completeness"], "far_completeness_sym": gen.get("far_completeness_sym"),
            "lateral_balance": gen["lateral_offset"],
            "consistency": gen["consistency"], "consistency_pairs": gen.get("consistency_pairs"),
            "instances": res["overall"]["count"],
        })
    return rows


def summary_markdown(rows: list[dict[str, Any]]) -> str:
    """The summary rows as a Markdown table (what ``--real-table`` writes for the README)."""
    def cell(value: Any, fmt: str = "{:.3f}") -> str:
        return "-" if value is None else fmt.format(value)

    lines = ["| backend | completeness | completeness, symmetric ref. | generated-only completeness (below mirror) "
             "| unseen half, generated | unseen half, generated, symmetric ref. | lateral balance, generated "
             "| consistency, generated |", "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        gain = "" if r["generated_gain_vs_mirror"] is None else f" ({100 * r['generated_gain_vs_mirror']:.1f} %)"
        lines.append(f"| {r['backend']} | {cell(r['completeness'])} | {cell(r.get('completeness_sym'))} | "
                     f"{cell(r['generated_completeness'])}{gain} | {cell(r['far_completeness'])} | "
                     f"{cell(r.get('far_completeness_sym'))} | {cell(r['lateral_balance'])} | "
                     f"{cell(r['consistency'])} |")
    return "\n".join(lines) + "\n"


def criteria(results: dict[str, Any]) -> dict[str, Any]:
    """The bars per learned backend: completeness (published and generated-only) >= 40 % below
    mirror's, the generated points' lateral balance <= 0.10 m, fidelity (and the generated points'
    fidelity) <= 2x the input's own spacing."""
    mirror = results.get("mirror", {}).get("overall", {}).get("completeness")
    out = {}
    for name, res in results.items():
        if not res.get("learned") or "overall" not in res or name.endswith(GENERATED_SUFFIX):
            continue
        o = res["overall"]
        gen = results.get(name + GENERATED_SUFFIX, res)["overall"]
        gain = None if not mirror else 1.0 - o["completeness"] / mirror
        gen_gain = None if not mirror else 1.0 - gen["completeness"] / mirror
        fid = o.get("fidelity_generated") if o.get("fidelity_generated") is not None else o["fidelity"]
        balance = gen.get("lateral_offset")
        out[name] = {
            "completeness_gain_vs_mirror": gain,
            "completeness_ok": gain is not None and gain >= GAIN_BAR,
            "generated_gain_vs_mirror": gen_gain,
            "generated_ok": gen_gain is not None and gen_gain >= GAIN_BAR,
            "lateral_balance": balance,
            "balance_ok": balance is not None and balance <= BALANCE_BAR_M,
            "consistency": gen.get("consistency"),
            "fidelity_over_spacing": o["fidelity"] / o["spacing"] if o.get("spacing") else None,
            "fidelity_generated_over_spacing": fid / o["spacing"] if o.get("spacing") else None,
            "fidelity_ok": bool(o.get("spacing")) and o["fidelity"] <= FIDELITY_BAR * o["spacing"],
        }
    return out


def print_real_tables(results: dict[str, Any]) -> None:
    scored = {n: r for n, r in results.items() if "overall" in r}
    columns = ["backend", "overall"] + [b[0] for b in DISTANCE_BANDS] + [b[0] for b in POINT_BANDS]
    for key in TABLE_METRICS:
        unit, lower, meaning = REAL_METRICS[key]
        rows = []
        for name, res in scored.items():
            if name == REFERENCE_ROW and key in ("completeness", "far_completeness", "fidelity", "fidelity_generated",
                                                 "side_cd", "consistency"):
                continue  # trivially zero / undefined for the reference itself (its *_sym rows: how one-sided it is)
            row = {"backend": name, "overall": res["overall"][key]}
            row.update({b: res["by_distance"][b][key] for b, _, _ in DISTANCE_BANDS})
            row.update({b: res["by_points"][b][key] for b, _, _ in POINT_BANDS})
            if key == "points":
                o = res["overall"]
                row["overall"] = (f"{metric_cell(o[key])} [{metric_cell(o.get('points_min'))}-"
                                  f"{metric_cell(o.get('points_max'))}]")
            rows.append({k: metric_cell(v) for k, v in row.items()})
        if key == "fidelity":  # the scan's own spacing, the yardstick of fidelity
            any_res = next(iter(scored.values()))
            row = {"backend": "(input spacing)", "overall": any_res["overall"]["spacing"]}
            row.update({b: any_res["by_distance"][b]["spacing"] for b, _, _ in DISTANCE_BANDS})
            row.update({b: any_res["by_points"][b]["spacing"] for b, _, _ in POINT_BANDS})
            rows.append({k: metric_cell(v) for k, v in row.items()})
        better = "" if lower is None else ("; lower is better" if lower else "; higher is better")
        print_table(f"{key} [{unit}{better}] {meaning}", rows, columns)
    first = next(iter(scored.values()))
    counts = {"backend": "instances", "overall": first["overall"]["count"]}
    counts.update({b: first["by_distance"][b]["count"] for b, _, _ in DISTANCE_BANDS})
    counts.update({b: first["by_points"][b]["count"] for b, _, _ in POINT_BANDS})
    print_table("instances per band", [counts], columns)


def pick_examples(instances: list[dict[str, Any]], count: int) -> list[int]:
    """Examples spread over the input point count (5-point and 1000-point cars both shown)."""
    if not instances or count < 1:
        return []
    order = np.argsort([len(i["partial"]) for i in instances], kind="stable")
    picks = np.linspace(0, len(order) - 1, min(count, len(order))).round().astype(int)
    return [int(order[p]) for p in np.unique(picks)]


@dataclass
class RealEvalConfig:
    """What ``pcc eval --real`` is told; the command builds it from its ``--real-*`` flags."""

    sources: list[Path]  # KITTI tracking / object, nuScenes roots or Argoverse 2 logs / split dirs
    backends: str | None = None  # comma-separated; None: every available backend
    checkpoints: dict[str, Path] = field(default_factory=dict)  # backend -> checkpoint (default: shipped)
    voxel: float = 0.03  # reference voxel size, metres
    min_points: int | None = None  # inputs with fewer points are skipped (None: completion_node's min_points)
    min_track_frames: int = 2  # observations a track needs (at least 2: a multi-view reference)
    detections: Path | None = None  # crop the inputs from these detector results instead of the labelled boxes
    matched_labels: bool = False  # with detections: crop the matched detections' labelled boxes (same observations)
    keep_input: bool = True  # score the published, partial-preserving output (False: generated points only)
    decode_density: int | None = None  # None: completion_node's decode_density
    device: str = "auto"  # auto runs on the CPU
    batch_size: int = 32
    json: Path | None = None
    plot: Path | None = None
    table: Path | None = None  # the summary as a Markdown table (the README's real-data table)
    plot_backends: str | None = None  # comma-separated completion columns of the PNG (None: every backend)
    examples: int = 4
    track_memory: str | None = None  # ids | nearest: complete each car from its accumulated crops (causal)
    mirror: bool = False  # every frame reflected across the sensor's x-z plane: the cars seen from their other flank


def run_real(opts: RealEvalConfig) -> int:
    """Evaluate ``opts.backends`` on the real sources: prints the tables and the issue's bar,
    writes ``opts.json`` / ``opts.plot`` when given."""
    sources = list(opts.sources)
    if not sources:
        raise ConfigError("--real-sources is empty")
    if opts.voxel <= 0:
        raise ConfigError(f"--real-voxel must be positive, got {opts.voxel}")
    backends = backend_names(opts.backends) if opts.backends else available()  # checked before the frames load
    checkpoints = dict(opts.checkpoints)
    unused = sorted(set(checkpoints) - set(backends))
    if unused:
        raise ConfigError(f"--checkpoint given for backend(s) not evaluated: {unused}")
    plotted = [b.strip() for b in (opts.plot_backends or "").split(",") if b.strip()]
    unplotted = [b for b in plotted if b.removesuffix(GENERATED_SUFFIX) not in backends]
    if unplotted:  # was: left out of the PNG without a word, after the whole evaluation
        raise ConfigError(f"--plot-backends names backend(s) not evaluated: {unplotted} (evaluated: "
                          f"{', '.join(backends)}; NAME{GENERATED_SUFFIX} is a learned backend's generated points)")
    detections = Path(opts.detections) if opts.detections else None
    boxes = "detections" if detections is not None else "ground_truth"
    instances, report = real_instances(sources, max(opts.min_track_frames, 2), opts.min_points, opts.voxel,
                                       boxes=boxes, detections_dir=detections, matched_labels=opts.matched_labels,
                                       mirror=opts.mirror)
    if not instances:
        raise DataError(f"no real instance with a multi-view reference in {', '.join(map(str, sources))}")
    log.info("evaluating %d real instance(s) of %d track(s)", len(instances),
             len({i["key"].split("@")[0] for i in instances}))
    device = "cpu" if opts.device == "auto" else opts.device
    accumulated, memory_ms = None, None
    if opts.track_memory:
        accumulated, memory_ms = track_memory_inputs(instances, opts.track_memory)
        log.info("track memory (%s): %.0f input points per instance on average (%.0f in the crops), %.3f ms per frame",
                 opts.track_memory, np.mean([len(a) for a in accumulated]),
                 np.mean([len(i["partial"]) for i in instances]), memory_ms)
    results, completions = evaluate_real(instances, backends, checkpoints, device, opts.batch_size,
                                         keep_input=opts.keep_input, decode_density=opts.decode_density,
                                         strict=bool(opts.backends), accumulated=accumulated)
    print_real_tables(results)
    verdict = criteria(results)
    summary = summary_rows(results)
    print_table("summary [m; lower is better]: published completeness; on the generated points (a baseline: its "
                "output): completeness, unseen half, lateral balance |mean y|, consistency between consecutive frames",
                [{k: metric_cell(v) for k, v in r.items()} for r in summary])
    met = {True: "met", False: "NOT met"}
    for name, v in verdict.items():
        print(f"{name}: completeness {100 * (v['completeness_gain_vs_mirror'] or 0):.1f} % below mirror, generated "
              f"points {100 * (v['generated_gain_vs_mirror'] or 0):.1f} % (bar 40 %: {met[v['completeness_ok']]} / "
              f"{met[v['generated_ok']]}); lateral balance {metric_cell(v['lateral_balance'])} m (bar "
              f"{BALANCE_BAR_M} m: {met[v['balance_ok']]}); consistency {metric_cell(v['consistency'])} m; fidelity "
              f"{v['fidelity_over_spacing']:.2f}x / generated points {v['fidelity_generated_over_spacing']:.2f}x "
              f"the input spacing (bar 2x: {met[v['fidelity_ok']]})")
    margin, ground_margin, _ = node_crop()
    out = {"mode": "real", "sources": report, "voxel_m": opts.voxel, "instances": len(instances),
           "boxes": "labels of matched detections" if opts.matched_labels else boxes, "mirror": opts.mirror,
           "input_crop": {"box_margin": margin, "ground_margin": ground_margin},
           "backends": results, "criteria": verdict, "summary": summary}
    if accumulated is not None:
        out["track_memory"] = {"association": opts.track_memory, "ms_per_frame": memory_ms,
                               "input_points_mean": float(np.mean([len(a) for a in accumulated])),
                               "crop_points_mean": float(np.mean([len(i["partial"]) for i in instances]))}
    if opts.table:
        opts.table.parent.mkdir(parents=True, exist_ok=True)
        opts.table.write_text(summary_markdown(summary))
        log.info("wrote %s", opts.table)
    if opts.plot:
        picks = pick_examples(instances, opts.examples)
        names = [n for n in completions if n != "input" and not n.endswith(GENERATED_SUFFIX)]
        if plotted:
            names = [n for n in plotted if n in completions]  # a backend that did not load has no column
        examples = []
        for p in picks:
            inst = instances[p]
            size = inst["size"]
            clouds = {"input": inst["partial"], **{n: completions[n][p] for n in names},
                      REFERENCE_ROW: inst["reference"]}
            examples.append({"label": f"{inst['key']}\n{inst['distance']:.0f} m, {len(inst['partial'])} pts",
                             "box": size / size[0] / 2, "length": size[0], "clouds": clouds})
        opts.plot.parent.mkdir(parents=True, exist_ok=True)
        draw_three_views(opts.plot, examples, ["input", *names, REFERENCE_ROW],
                         "real completions (metres about the box centre; grey: labelled box)")
        out["plot"] = {"path": str(opts.plot), "instances": [instances[p]["key"] for p in picks]}
        log.info("wrote %s", opts.plot)
    if opts.json:
        write_results(opts.json, out)
        log.info("wrote %s", opts.json)
    return 0
