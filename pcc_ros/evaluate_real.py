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

import argparse
import json
import logging
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from pcc_ros.errors import BackendError, CheckpointError, ConfigError, DataError

log = logging.getLogger("pcc.eval.real")

#: Tables printed, in order (``spacing`` is printed with fidelity for comparison).
TABLE_METRICS = ("completeness", "fidelity", "fidelity_generated", "side_cd", "inside_box", "bottom_gap", "top_gap",
                 "lateral_offset", "points")
REFERENCE_ROW = "aggregated GT"


def real_instances(
    sources: list[Path], min_track_frames: int = 2, min_points: int = 3, voxel_m: float = 0.03,
    classes: tuple[str, ...] = ("Car", "Van"),
) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """Evaluation instances of the labelled real ``sources`` and a report of what was skipped.

    Each instance: ``key``, ``partial`` (canonical), ``reference`` (the track's voxel-thinned
    aggregate), ``size`` (box l, w, h), ``distance``, ``track_frames``.
    """
    from pcc_ros.data.sources import open_frames
    from pcc_ros.data.track_aggregate import collect_tracks

    instances: list[dict[str, Any]] = []
    report: dict[str, Any] = {}
    for source in sources:
        if not source.exists():
            raise DataError(f"{source}: real dataset not found (pass --real-sources)")
        skipped: Counter = Counter()
        tracks = collect_tracks(open_frames(source), classes=classes, skipped=skipped)
        used = 0
        for track in tracks.values():  # loop over tracks; points are vectorised inside
            if len(track) < min_track_frames:
                skipped["track_too_short"] += len(track)
                continue
            reference = track.aggregate(voxel_m=voxel_m)
            for obs in track.observations:
                if obs.num_points < min_points:
                    skipped["input_too_few_points"] += 1
                    continue
                instances.append({"key": f"{source.name}:{obs.key}", "partial": obs.points, "reference": reference,
                                  "size": np.asarray(obs.size, dtype=np.float64), "distance": obs.distance,
                                  "track_frames": len(track), "label": obs.label,
                                  "frame_key": f"{source}:{obs.sequence}:{obs.frame}",
                                  "center": np.asarray(obs.center, dtype=np.float64), "yaw": obs.yaw})
                used += 1
        report[str(source)] = {"tracks": len(tracks), "instances": used, "skipped": dict(skipped)}
        if used == 0:
            log.info("%s: no track with >= %d observations (a single-frame dataset has no multi-view "
                     "reference): skipped %s", source, min_track_frames, dict(skipped))
        elif skipped:
            log.info("%s: %d instances; skipped %s", source, used, dict(skipped))
    return instances, report


def _bands(instances: list[dict[str, Any]], rows: list[dict[str, float]]) -> dict[str, Any]:
    from pcc_ros.evaluate import DISTANCE_BANDS, POINT_BANDS
    from pcc_ros.metrics.realdata import mean_rows

    distance = np.array([i["distance"] for i in instances])
    points = np.array([len(i["partial"]) for i in instances])
    return {
        "overall": mean_rows(rows, np.ones(len(instances), bool)),
        "by_distance": {b: mean_rows(rows, (distance >= lo) & (distance < hi)) for b, lo, hi in DISTANCE_BANDS},
        "by_points": {b: mean_rows(rows, (points >= lo) & (points < hi)) for b, lo, hi in POINT_BANDS},
    }


def scene_contexts(instances: list[dict[str, Any]]) -> list[Any]:
    """One :class:`~pcc_ros.models.base.SceneContext` per instance: the other evaluated cars of
    the same frame are its neighbours (what the pipeline gives a context-using backend)."""
    from pcc_ros.models.base import SceneContext
    from pcc_ros.types import Boxes

    contexts: list[Any] = [None] * len(instances)
    groups: dict[str, list[int]] = {}
    for i, inst in enumerate(instances):
        groups.setdefault(inst["frame_key"], []).append(i)
    for members in groups.values():  # loop over frames; a handful of cars each
        boxes = Boxes(np.stack([instances[i]["center"] for i in members]),
                      np.stack([instances[i]["size"] for i in members]),
                      np.array([instances[i]["yaw"] for i in members]),
                      np.array([instances[i]["label"] for i in members], dtype=object))
        for i, ctx in zip(members, SceneContext.from_frame(boxes, [instances[i]["partial"] for i in members])):
            contexts[i] = ctx
    return contexts


def evaluate_real(
    instances: list[dict[str, Any]], backends: list[str], checkpoints: dict[str, Path], device: str = "cpu",
    batch_size: int = 32, progress: bool = True, with_input: bool = True,
) -> tuple[dict[str, Any], dict[str, list[np.ndarray]]]:
    """Complete every instance with every backend (batched) and score it.

    ``with_input``: also score each learned backend's completion united with the input crop
    (row ``NAME+input``), since a consumer of the node's output gets both. Backends that read
    scene context (TraPCC) get the other evaluated cars of the frame as neighbours."""
    from tqdm import tqdm

    from pcc_ros.metrics.realdata import real_instance_metrics
    from pcc_ros.models import get_backend, load_completer

    results: dict[str, Any] = {}
    completions: dict[str, list[np.ndarray]] = {}
    partials = [i["partial"] for i in instances]
    ref_rows = [real_instance_metrics(i["reference"], i["partial"], i["reference"], i["size"]) for i in instances]
    for name in backends:
        try:
            cls = get_backend(name)
            options = {"batch_size": batch_size} if cls.learned else {}
            completer = load_completer(name, checkpoints.get(name), device=device, **options)
        except (CheckpointError, BackendError) as exc:
            log.warning("%s: skipped (%s)", name, exc)
            results[name] = {"skipped": str(exc)}
            continue
        contexts = scene_contexts(instances) if getattr(completer, "uses_context", False) else None
        outs: list[np.ndarray] = []
        for start in tqdm(range(0, len(partials), 64), desc=f"complete {name}", disable=not progress, leave=False):
            chunk = None if contexts is None else contexts[start : start + 64]
            outs.extend(completer.complete(partials[start : start + 64], chunk))
        rows = [real_instance_metrics(o, i["partial"], i["reference"], i["size"]) for o, i in zip(outs, instances)]
        results[name] = {**_bands(instances, rows), "learned": bool(cls.learned)}
        if cls.learned:
            ck = getattr(completer, "checkpoint_config", None) or {}
            results[name]["checkpoint"] = str(checkpoints.get(name, "shipped default"))
            results[name]["checkpoint_sha256"] = ck.get("sha256")
        completions[name] = outs
        if cls.learned and with_input:
            # The completion together with the car's own crop: what completion_node publishes
            # with include_input_points (raw scan, instance -1, plus the completion).
            union = [np.concatenate([o, i["partial"].astype(np.float32)]) for o, i in zip(outs, instances)]
            rows = [real_instance_metrics(o, i["partial"], i["reference"], i["size"])
                    for o, i in zip(union, instances)]
            results[f"{name}+input"] = {**_bands(instances, rows), "learned": True,
                                        "variant": f"{name} completion plus the input crop"}
            completions[f"{name}+input"] = union
    results[REFERENCE_ROW] = {**_bands(instances, ref_rows), "learned": False}
    return results, completions


def criteria(results: dict[str, Any]) -> dict[str, Any]:
    """The issue's bar per learned backend: completeness >= 40 % below mirror's, fidelity
    (and the generated points' fidelity) <= 2x the input's own spacing."""
    mirror = results.get("mirror", {}).get("overall", {}).get("completeness")
    out = {}
    for name, res in results.items():
        if not res.get("learned") or "overall" not in res:
            continue
        o = res["overall"]
        gain = None if not mirror else 1.0 - o["completeness"] / mirror
        fid = o.get("fidelity_generated") if o.get("fidelity_generated") is not None else o["fidelity"]
        out[name] = {
            "completeness_gain_vs_mirror": gain,
            "completeness_ok": gain is not None and gain >= 0.4,
            "fidelity_over_spacing": o["fidelity"] / o["spacing"] if o.get("spacing") else None,
            "fidelity_generated_over_spacing": fid / o["spacing"] if o.get("spacing") else None,
            "fidelity_ok": bool(o.get("spacing")) and o["fidelity"] <= 2 * o["spacing"],
        }
    return out


def print_real_tables(results: dict[str, Any]) -> None:
    from pcc_ros.evaluate import DISTANCE_BANDS, POINT_BANDS, _cell
    from pcc_ros.metrics.realdata import REAL_METRICS
    from pcc_ros.tables import print_table

    scored = {n: r for n, r in results.items() if "overall" in r}
    columns = ["backend", "overall"] + [b[0] for b in DISTANCE_BANDS] + [b[0] for b in POINT_BANDS]
    for key in TABLE_METRICS:
        unit, lower, meaning = REAL_METRICS[key]
        rows = []
        for name, res in scored.items():
            if name == REFERENCE_ROW and key in ("completeness", "fidelity", "fidelity_generated", "side_cd"):
                continue  # trivially zero / undefined for the reference itself
            row = {"backend": name, "overall": res["overall"][key]}
            row.update({b: res["by_distance"][b][key] for b, _, _ in DISTANCE_BANDS})
            row.update({b: res["by_points"][b][key] for b, _, _ in POINT_BANDS})
            if key == "points":
                row["overall"] = f"{_cell(res['overall'][key])} [{_cell(res['overall'].get('points_min'))}-" \
                                 f"{_cell(res['overall'].get('points_max'))}]"
            rows.append({k: _cell(v) for k, v in row.items()})
        if key == "fidelity":  # the scan's own spacing, the yardstick of fidelity
            any_res = next(iter(scored.values()))
            row = {"backend": "(input spacing)", "overall": any_res["overall"]["spacing"]}
            row.update({b: any_res["by_distance"][b]["spacing"] for b, _, _ in DISTANCE_BANDS})
            row.update({b: any_res["by_points"][b]["spacing"] for b, _, _ in POINT_BANDS})
            rows.append({k: _cell(v) for k, v in row.items()})
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


def run_real(args: argparse.Namespace) -> int:
    from pcc_ros.evaluate import _write_json, parse_checkpoints
    from pcc_ros.metrics.realdata import draw_three_views
    from pcc_ros.models import available

    sources = [Path(s.strip()) for s in args.real_sources.split(",") if s.strip()]
    if not sources:
        raise ConfigError("--real-sources is empty")
    if args.real_voxel <= 0:
        raise ConfigError(f"--real-voxel must be positive, got {args.real_voxel}")
    backends = [b.strip() for b in args.backends.split(",") if b.strip()] if args.backends else available()
    checkpoints = parse_checkpoints(args.checkpoint)
    unused = sorted(set(checkpoints) - set(backends))
    if unused:
        raise ConfigError(f"--checkpoint given for backend(s) not evaluated: {unused}")
    instances, report = real_instances(sources, max(args.min_track_frames, 2), args.real_min_points, args.real_voxel)
    if not instances:
        raise DataError(f"no real instance with a multi-view reference in {', '.join(map(str, sources))}")
    log.info("evaluating %d real instance(s) of %d track(s)", len(instances),
             len({i["key"].split("@")[0] for i in instances}))
    device = "cpu" if args.device == "auto" else args.device
    results, completions = evaluate_real(instances, backends, checkpoints, device, args.batch_size)
    print_real_tables(results)
    verdict = criteria(results)
    for name, v in verdict.items():
        print(f"{name}: completeness {100 * (v['completeness_gain_vs_mirror'] or 0):.1f} % below mirror "
              f"(bar 40 %: {'met' if v['completeness_ok'] else 'NOT met'}); fidelity "
              f"{v['fidelity_over_spacing']:.2f}x / generated points {v['fidelity_generated_over_spacing']:.2f}x "
              f"the input spacing (bar 2x: {'met' if v['fidelity_ok'] else 'NOT met'})")
    out = {"mode": "real", "sources": report, "voxel_m": args.real_voxel, "instances": len(instances),
           "backends": results, "criteria": verdict}
    if args.plot:
        picks = pick_examples(instances, args.examples)
        names = [n for n in completions if n != "input"]
        examples = []
        for p in picks:
            inst = instances[p]
            size = inst["size"]
            clouds = {"input": inst["partial"], **{n: completions[n][p] for n in names},
                      REFERENCE_ROW: inst["reference"]}
            examples.append({"label": f"{inst['key']}\n{inst['distance']:.0f} m, {len(inst['partial'])} pts",
                             "box": size / size[0] / 2, "length": size[0], "clouds": clouds})
        args.plot.parent.mkdir(parents=True, exist_ok=True)
        draw_three_views(args.plot, examples, ["input", *names, REFERENCE_ROW],
                         "real completions (metres about the box centre; grey: labelled box)")
        out["plot"] = {"path": str(args.plot), "instances": [instances[p]["key"] for p in picks]}
        log.info("wrote %s", args.plot)
    if args.json:
        _write_json(args.json, json.loads(json.dumps(out, default=float)))
        log.info("wrote %s", args.json)
    return 0
