"""``pcc calibrate-filter --sim-sensors ...`` / ``--sensor X``: one rule across sensors.

The command half of :mod:`pcc_ros.workflows.filter_sensors` (which says what is fitted and how): the
simulated sets are generated (once, cached), every detection measured, the rule fitted and
cross-validated by sensor and by sequence, the ablation run; the node YAML (``--out``) and the
report (``--json``) written.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
from dataclasses import replace
from typing import Any

import numpy as np

from pcc_ros.errors import ConfigError
from pcc_ros.files import write_json, write_text
from pcc_ros.geometry.beams import SENSOR_PRESETS
from pcc_ros.pipeline.config import PipelineConfig
from pcc_ros.pipeline.filter import TERMS, FilterConfig, format_sensor_thresholds
from pcc_ros.workflows.detection_eval import default_config, load_kitti, parse_frames
from pcc_ros.workflows.filter_calibration import preset_yaml
from pcc_ros.workflows.filter_sensors import (
    SENSOR_TERMS,
    Rows,
    calibrate_sensors,
    measuring_pipeline,
    parse_terms,
    real_rows,
    rows_probability,
    synth_dataset,
    synth_rows,
)
from pcc_ros.workflows.sensor_thresholds import cached_rows, fallback_threshold, sensor_thresholds

log = logging.getLogger(__name__)


def _line(name: str, fig: dict[str, Any]) -> str:
    kinds = ", ".join(f"{k} {v['removed']:.0%}" for k, v in fig["per_kind"].items())
    return (f"{name}: {fig['false_removed']:.1%} false removed, {fig['true_lost']:.1%} true lost at the fold "
            f"thresholds; best at <= 2 % lost {fig['false_removed_at_0.02_lost_best']:.1%}; AUC "
            f"{fig['auc_false_above_true']:.3f}; per kind: {kinds}")


def labelled_real_rows(args: argparse.Namespace, pipeline) -> Rows:
    """The rows of ``--real``'s labelled frames with ``--real-detections``' boxes (their scores read
    with ``--score-mapping``)."""
    if args.real_detections is None:
        raise ConfigError("--real needs --real-detections (the real detector's results)")
    pipeline.config = replace(pipeline.config, filter=replace(pipeline.config.filter, score_mapping=args.score_mapping))
    classes = tuple(c.strip() for c in args.gt_classes.split(",") if c.strip())
    frames = load_kitti(args.real, args.real_detections, args.real_sequence, parse_frames(args.real_frames))
    return real_rows(pipeline, frames, args.sensor, classes)


def run_sensors(args: argparse.Namespace) -> int:
    if args.sim_sensors:
        sensors = tuple(s.strip() for s in args.sim_sensors.split(",") if s.strip())
    elif args.sensor and args.sensor != "auto":
        sensors = (args.sensor,)  # the labelled-frame-free path: simulation of that sensor only
    else:
        raise ConfigError("give --real (labelled frames), --sim-sensors, or --sensor NAME (simulation only)")
    terms = parse_terms(args.terms, SENSOR_TERMS)
    pipeline = measuring_pipeline(args.filter_backend, shape="mismatch" in terms)
    parts = []
    single = len(sensors) == 1 and args.real is None  # --sensor X: that sensor's own beam model
    for layout in sensors:
        root = synth_dataset(args.sim_root, layout, args.sim_seed, args.sim_sequences, args.sim_frames)
        parts.append(synth_rows(pipeline, root, layout, layout) if single
                     else cached_rows(pipeline, root, layout, args.rows_cache, "mismatch" in terms))
    if args.real is not None:
        parts.append(labelled_real_rows(args, pipeline))
    rows = Rows.concatenate(parts)
    result = calibrate_sensors(rows, terms, args.max_lost, args.l2, args.target_lost)
    print("rows:", json.dumps(result["rows"]))
    selection = result.get("budget_selection")
    if selection is not None:
        print(f"loss budget by leave-one-sensor-out CV (target <= {selection['target_lost']:.1%} of a held-out "
              "sensor's true cars): " + ", ".join(f"{b:.2%} -> worst {w:.2%}" for b, w in
                                                  zip(selection["grid"], selection["worst_held_out_lost"]))
              + f"; chosen {selection['chosen']:.2%}")
        for s, n in selection.get("nested", {}).items():
            if n["budget"] is not None:
                print(f"  {s} held out of the choice too: budget {n['budget']:.2%}, {n['true_lost']:.1%} of its true "
                      f"lost, {n['false_removed']:.1%} of its false removed")
    print("weights:", " ".join(f"w_{t}={w:+.4f}" for t, w in result["weights"].items()),
          f"w_bias={result['bias']:+.4f} reject_threshold={result['threshold']:.4f}")
    if "cv_by_sensor" in result:
        for s, fig in result["cv_by_sensor"]["folds"].items():
            print(_line(f"held-out sensor {s}", fig))
    print(_line("held-out sequences (pooled)", result["cv_by_sequence"]["pooled"]))
    if "cv_real_frames" in result:
        print(_line("held-out real frames", result["cv_real_frames"]))
    for t, a in result["ablation"].items():
        print(f"without {t}: held-out AUC {a['auc_without']:.3f} ({a['auc_change']:+.3f} for the term), removed at "
              f"<= 2 % lost {a['removed_at_0.02_without']:.1%} ({a['removed_at_0.02_change']:+.1%})")
    for t, kinds in result["term_auc"].items():
        print(f"{t} alone, AUC false above true: " + ", ".join(f"{k} {v:.3f}" for k, v in kinds.items()))
    m = result.get("mismatch")
    if m is None:
        print("mismatch: not among the fitted terms (weight 0)")
    else:
        print(f"mismatch: weight {m['weight']:+.4f}; alone, AUC confusions vs true cars "
              f"{m['auc_alone_confusion_vs_true']:.3f}"
              f" (all false {m['auc_alone_all_false_vs_true']:.3f}); held-out AUC on confusions with / without it "
              f"{m['confusion_auc_held_out_with']:.3f} / {m['confusion_auc_held_out_without']:.3f}")
    sensor_value = "auto" if len(sensors) > 1 or args.real is not None else sensors[0]
    weights = np.array([result["weights"][t] for t in TERMS])
    per_sensor = None
    if args.sensor_thresholds:
        fitted = FilterConfig(w_bias=result["bias"], **{f"w_{t}": float(w) for t, w in zip(TERMS, weights)},
                              mismatch_mean=result["mismatch_mean"], sensor_thresholds="", trees="")
        rows_of = layout_rows(args, pipeline, "mismatch" in terms)
        per_sensor = per_sensor_step(args, rows_of, {k: rows_probability(r, fitted, None) for k, r in rows_of.items()},
                                     result["threshold"])
        result["sensor_thresholds"] = per_sensor
    if args.out:
        values: dict[str, Any] = {"sensor": sensor_value, "score_mapping": "identity"}
        if weights[TERMS.index("mismatch")] != 0:
            values["filter_backend"] = args.filter_backend
        values["mismatch_mean"] = round(float(result["mismatch_mean"]), 4)
        real = f" --real {args.real} --real-detections {args.real_detections}" if args.real else ""
        header = (f"# calibrated: pcc calibrate-filter --sim-sensors {','.join(sensors)} --sim-seed {args.sim_seed}"
                  f" --sim-sequences {args.sim_sequences} --sim-frames {args.sim_frames}"
                  f"{real}"
                  f" --terms {','.join(terms)} --max-lost {args.max_lost}"
                  f"{f' --target-lost {args.target_lost:g}' if selection is not None else ''} --out {args.out}\n")
        if selection is not None:
            header += (f"# calibrated: loss budget by leave-one-sensor-out CV, the largest of {selection['grid']} "
                       f"whose held-out sensors each lose <= {selection['target_lost']:g} of their true cars "
                       f"(worst held-out loss per budget: {[round(w, 4) for w in selection['worst_held_out_lost']]}): "
                       f"{selection['chosen']:g}\n")
        threshold = result["threshold"]
        if per_sensor is not None:
            values["sensor_thresholds"] = per_sensor["value"]
            threshold = per_sensor["fallback"]
            header += per_sensor_header(args, per_sensor)
        text = preset_yaml(args.base_config or default_config(), result["bias"], weights, threshold, values, header)
        args.out.parent.mkdir(parents=True, exist_ok=True)
        write_text(args.out, text)
        log.info("wrote %s", args.out)
    if args.json:
        write_report(args.json, {"sensors": list(sensors), "sim_seed": args.sim_seed, **result})
    return 0


# ----------------------------------------------------------------------------- per-sensor thresholds


def threshold_layouts(text: str) -> tuple[str, ...]:
    """``--sensor-thresholds``: preset names, comma-separated, or ``all``."""
    if text.strip().lower() == "all":
        return tuple(SENSOR_PRESETS)
    layouts = tuple(t.strip() for t in text.split(",") if t.strip())
    unknown = [t for t in layouts if t not in SENSOR_PRESETS]
    if unknown or not layouts:
        raise ConfigError(f"--sensor-thresholds: unknown layout(s) {unknown} (have all, {', '.join(SENSOR_PRESETS)})")
    return layouts


def layout_rows(args: argparse.Namespace, pipeline, shape: bool) -> dict[str, Rows]:
    """Each ``--sensor-thresholds`` layout's rows: its simulated set measured or read from ``--rows-cache``."""
    rows = {}
    for layout in threshold_layouts(args.sensor_thresholds):
        root = synth_dataset(args.sim_root, layout, args.sim_seed, args.sim_sequences, args.sim_frames)
        rows[layout] = cached_rows(pipeline, root, layout, args.rows_cache, shape)
    return rows


def per_sensor_step(args: argparse.Namespace, rows: dict[str, Rows], p: dict[str, np.ndarray],
                    reject_threshold: float | None) -> dict[str, Any]:
    """Each layout's threshold for one rule (``p``: each layout's p_false under it), printed; the
    table, its parameter string and the fallback (the largest of the table and ``reject_threshold``,
    the rule's own where it has one)."""
    table = sensor_thresholds(rows, p, args.target_lost, per_fold=args.threshold_folds)
    fallback = fallback_threshold(table, 0.0 if reject_threshold is None else reject_threshold)
    print(f"per-sensor thresholds (budget by CV over folds of {args.threshold_folds} sequence(s), each held-out fold "
          f"<= {args.target_lost:.1%} of its true cars lost):")
    for layout, t in table.items():
        print(f"  {layout}: threshold {t['threshold']:.4f}, budget {t['budget']:.2%}, worst held-out fold "
              f"{t['cv_worst_fold']:.2%} (pooled {t['cv_pooled']:.2%}) of {t['rows']['true']} true; on its rows "
              f"{t['in_sample_removed']:.1%} of {t['rows']['false']} false removed")
    print(f"  no preset matched: reject_threshold {fallback:.4f} (the largest of these"
          f"{'' if reject_threshold is None else f' and {reject_threshold:.4f}'})")
    return {"layouts": table, "value": format_sensor_thresholds({k: v["threshold"] for k, v in table.items()}),
            "fallback": fallback, "sequences_per_fold": args.threshold_folds, "target_lost": args.target_lost}


def per_sensor_header(args: argparse.Namespace, per_sensor: dict[str, Any], source: str | None = None) -> str:
    """The YAML header lines that say where ``sensor_thresholds`` came from (``source``: the command
    that set them, when it is not the ``--sensor-thresholds`` step's own)."""
    table = ", ".join(f"{k} {v['threshold']:.4f} / {v['budget']:.2%} / {v['cv_worst_fold']:.2%}"
                      for k, v in per_sensor["layouts"].items())
    command = source or (
        f"pcc calibrate-filter --sensor-thresholds {args.sensor_thresholds}"
        f"{' --weights-from ' + str(args.weights_from) if args.weights_from and not args.sim_sensors else ''}"
        f" --sim-root {args.sim_root} --sim-seed {args.sim_seed} --sim-sequences {args.sim_sequences}"
        f" --sim-frames {args.sim_frames} --threshold-folds {args.threshold_folds} --target-lost {args.target_lost:g}")
    return (f"# calibrated: sensor_thresholds: {command}\n"
            f"# calibrated: sensor_thresholds per layout (threshold / budget / worst held-out fold of "
            f"{per_sensor['sequences_per_fold']} sequences): {table}; reject_threshold, for a sensor matching no "
            f"preset: the largest, {per_sensor['fallback']:.4f}\n")


def _weights_provenance(source, keep_trees: bool = True) -> str:
    """The ``# calibrated:`` lines of ``source`` that say where its weights (``keep_trees``: and its
    trees) came from, not its thresholds: a file that keeps them and sets new thresholds keeps these."""
    dropped = ("# calibrated: sensor_thresholds", *(() if keep_trees else ("# calibrated: trees",)))
    try:
        return "".join(line + "\n" for line in source.read_text().splitlines()
                       if line.startswith("# calibrated:") and not line.startswith(dropped))
    except OSError as exc:
        raise ConfigError(f"{source}: cannot read ({exc.strerror})") from exc


def kept_weights(args: argparse.Namespace):
    """The node YAML whose weights a threshold step keeps (``--weights-from``, else ``--base-config``,
    else the shipped one) and its filter parameters; refused unless it holds the evidence rule."""
    source = args.weights_from or args.base_config or default_config()
    config = PipelineConfig.from_yaml(source).filter
    if config.rule != "evidence":
        raise ConfigError(f"{source}: rule {config.rule!r}; per-sensor thresholds are the evidence rule's")
    return source, config


def write_kept_weights(args: argparse.Namespace, source, config, threshold: float, table: str, header: str,
                        keep_trees: bool = True) -> None:
    """``--out``: ``source`` with its weights (and the trees boosted from them, ``config.trees``) and
    their provenance kept, ``threshold`` as ``reject_threshold`` and ``table`` as
    ``sensor_thresholds``, under ``header``."""
    values: dict[str, Any] = {"sensor_thresholds": table, "mismatch_mean": config.mismatch_mean, "trees": config.trees}
    text = preset_yaml(source, config.w_bias, config.weights, threshold, values,
                       _weights_provenance(source, keep_trees) + header)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    write_text(args.out, text)
    log.info("wrote %s", args.out)


def write_report(path, payload: dict[str, Any]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    write_json(path, payload, indent=1, nonfinite_null=True)


def run_sensor_thresholds(args: argparse.Namespace) -> int:
    """``--sensor-thresholds`` without ``--sim-sensors``: the weights of ``--weights-from`` (or the
    base / shipped YAML) kept as they are, each layout's threshold added to ``--out``."""
    source, config = kept_weights(args)
    pipeline = measuring_pipeline(args.filter_backend, shape=config.w_mismatch != 0)
    rows = layout_rows(args, pipeline, config.w_mismatch != 0)
    p = {k: rows_probability(r, config, config.term_trees) for k, r in rows.items()}
    per_sensor = per_sensor_step(args, rows, p, config.reject_threshold)
    if args.out:
        write_kept_weights(args, source, config, per_sensor["fallback"], per_sensor["value"],
                            per_sensor_header(args, per_sensor))
    if args.json:
        write_report(args.json, {"weights_from": str(source), "sim_seed": args.sim_seed,
                                  "sim_root": str(args.sim_root), "sensor_thresholds": per_sensor})
    return 0


# ----------------------------------------------------------------------------- the user's own sensor


def run_sensor_from_scans(args: argparse.Namespace) -> int:
    """``--sensor-from SCANS``: the user's sensor read from its scans, simulated, and its threshold
    for the weights of ``--weights-from`` (else the base / shipped YAML) set by cross-validation over
    its simulated streets; ``--out`` holds that threshold for every sensor (no per-preset table)."""
    from pcc_ros.workflows.sensor_from_scans import scanned_sensor

    scanned = scanned_sensor(args.sensor_from, args.sensor_scans, height=args.sensor_height)
    m = scanned.model
    print(scanned.describe())
    if scanned.preset:
        print(f"  it matches the preset {scanned.preset}: the shipped sensor_thresholds already hold a threshold for "
              "it; this run sets one from your sensor's own simulation")
    source, config = kept_weights(args)
    trees = config.term_trees
    if trees is not None and trees.provenance.get("sim_seed") == args.sim_seed:
        log.warning("--sim-seed %d: the trees of %s were boosted on that seed's streets; a threshold set on scenes "
                    "they saw is optimistic (it loses more than --target-lost on streets they did not): give another "
                    "seed", args.sim_seed, source)
    sensor = scanned.sensor()
    key = hashlib.sha256(json.dumps(sensor.to_dict(), sort_keys=True).encode()).hexdigest()[:10]
    name = f"scanned_{key}"
    root = synth_dataset(args.sim_root, name, args.sim_seed, args.sim_sequences, args.sim_frames, sensor)
    pipeline = measuring_pipeline(args.filter_backend, shape=config.w_mismatch != 0)
    rows = cached_rows(pipeline, root, name, args.rows_cache, config.w_mismatch != 0)
    fit = sensor_thresholds({name: rows}, {name: rows_probability(rows, config, config.term_trees)}, args.target_lost,
                            per_fold=args.threshold_folds)[name]
    print(f"threshold {fit['threshold']:.4f}: budget {fit['budget']:.2%} by CV over {fit['folds']} folds of "
          f"{args.threshold_folds} simulated sequence(s), worst held-out fold {fit['cv_worst_fold']:.2%} of its true "
          f"cars lost (<= {args.target_lost:.1%}); in sample {fit['in_sample_removed']:.1%} of "
          f"{fit['rows']['false']} false boxes removed ({root})")
    if args.out:
        header = (f"# calibrated: pcc calibrate-filter --sensor-from {args.sensor_from}"
                  f" --sensor-scans {args.sensor_scans}"
                  f"{'' if args.sensor_height is None else f' --sensor-height {args.sensor_height:g}'}"
                  f" --sim-root {args.sim_root} --sim-seed {args.sim_seed}"
                  f" --sim-sequences {args.sim_sequences}"
                  f" --sim-frames {args.sim_frames} --threshold-folds {args.threshold_folds}"
                  f" --target-lost {args.target_lost:g} (weights of {source})\n"
                  f"# calibrated: the sensor: {m.rings} beams {m.elevations_deg[0]:+.2f}..{m.elevations_deg[-1]:+.2f}"
                  f" deg, step {m.azimuth_resolution_deg:.4f} deg, {scanned.mount_height:.2f} m high; threshold "
                  f"{fit['threshold']:.4f} (budget {fit['budget']:.2%}, worst held-out fold {fit['cv_worst_fold']:.2%})"
                  " for every sensor\n")
        write_kept_weights(args, source, config, fit["threshold"], "", header)
    if args.json:
        write_report(args.json, {"sensor": scanned.to_dict(), "weights_from": str(source), "sim_root": str(root),
                                  "threshold": fit})
    return 0
