"""Fit the detection filter's evidence weights and reject threshold (SynthCars + real frames).

The command half of :mod:`pcc_ros.workflows.filter_calibration` (which says what is fitted and how):
flags in; the calibration rows, weights, figures, the node YAML (``--out``) and JSON out.
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path
from typing import Any

import numpy as np

from pcc_ros.data.kitti import split_dir
from pcc_ros.errors import ConfigError
from pcc_ros.files import write_json, write_text
from pcc_ros.pipeline.filter import TERMS, FilterConfig
from pcc_ros.pipeline.parameters import CHOICES
from pcc_ros.workflows.detection_eval import default_config, load_kitti, parse_frames
from pcc_ros.workflows.filter_calibration import (
    FIT_TERMS,
    PRESET_NOTES,
    PRESETS,
    calibrate,
    cross_validate,
    preset_yaml,
)
from pcc_ros.workflows.filter_sensors import DEFAULT_SENSORS, SENSOR_TERMS, parse_terms

log = logging.getLogger(__name__)


SENSOR_CHOICES = CHOICES["sensor"]
#: ``--sim-seed`` of ``--sensor-from``: streets no shipped calibration used (the weights' and trees'
#: are seed 11's; a threshold set on scenes the trees were boosted on loses more than its budget).
SENSOR_FROM_SEED = 2027


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--real", type=Path, help="labelled KITTI root with real detections")
    parser.add_argument("--real-detections", type=Path, help="the real detector's results (with --real)")
    parser.add_argument(
        "--sim-sensors",
        help="fit ONE rule across SynthCars simulated with these beam layouts (comma-separated, e.g. "
        f"{','.join(DEFAULT_SENSORS)}), plus --real if given; cross-validated by sensor and by sequence, with an "
        "ablation. Without --real and without this flag, --sensor X calibrates for sensor X from simulation alone",
    )
    parser.add_argument("--sim-root", type=Path, default=Path("data/synthcars_sensors"),
                        help="where the simulated sets are generated once and reused (data/synthcars_sensors)")
    parser.add_argument("--sim-seed", type=int,
                        help="seed of the simulated sets (11; with --sensor-from 2027: not a seed the shipped trees "
                        "were boosted on, whose scenes would make the threshold optimistic)")
    parser.add_argument("--sim-sequences", type=int, help="SynthCars sequences per sensor (2; 8 with --sensor-from)")
    parser.add_argument("--sim-frames", type=int, help="frames per simulated sequence (6; 20 with --sensor-from)")
    parser.add_argument("--filter-backend", default="trapcc",
                        help="car-constrained completion of the shape mismatch term (trapcc)")
    parser.add_argument("--real-sequence", help="tracking sequence(s) of --real, comma-separated")
    parser.add_argument("--real-frames", help="START:STOP of --real's scans")
    parser.add_argument("--synth", type=Path, help="SynthCars root (pcc synth) with detections/synthetic")
    parser.add_argument("--synth-frames", type=int, default=20, help="frames used per SynthCars sequence (20)")
    parser.add_argument("--object", type=Path, help="KITTI object root: real scans, labelled cars as true detections")
    parser.add_argument("--gt-classes", default="Car,Van", help="labels that make a real detection true (Car,Van)")
    parser.add_argument("--score-mapping", choices=("identity", "sigmoid"), default="sigmoid",
                        help="how the real detector's scores read (sigmoid: logits, PointRCNN)")
    parser.add_argument("--sensor", default="auto", choices=SENSOR_CHOICES,
                        help="beam model: auto (estimated from each scan, the default) or a preset")
    parser.add_argument(
        "--max-lost", type=_budget, default=0.01,
        help="share of each source's (each sensor's) true detections the threshold may lose (0.01), or 'cv': "
        "across sensors, the largest budget of a grid (0.5-2 %%) whose leave-one-sensor-out folds each lose at "
        "most --target-lost of the held-out sensor's true cars")
    parser.add_argument("--target-lost", type=float, default=0.02,
                        help="with --max-lost cv: the most of a held-out sensor's true cars a fold may lose (0.02)")
    parser.add_argument("--l2", type=float, default=1e-2, help="ridge penalty on standardised weights (0.01)")
    parser.add_argument("--folds", type=int, default=5, help="leave-frames-out folds over the real frames (5; 0: none)")
    parser.add_argument("--seed", type=int, default=0, help="simulator seed")
    parser.add_argument("--terms",
                        help=f"terms to fit, comma-separated (default {','.join(FIT_TERMS)} with --real alone, "
                        f"{','.join(SENSOR_TERMS)} across sensors; the rest get weight 0)")
    parser.add_argument("--base-config", type=Path, help="node YAML to start from (default: the shipped one)")
    parser.add_argument("--out", type=Path, help="write the calibrated node YAML here")
    parser.add_argument(
        "--preset", choices=tuple(PRESETS), default="kitti",
        help="what --out is for: kitti (the fitted sensor model; writes score_mapping: identity, the shipped "
        "files' convention: run a logit detector with score_mapping:=sigmoid) | nuscenes (sensor auto, "
        "probability scores; the same physics weights: no real nuScenes detections to fit on)",
    )
    parser.add_argument("--json", type=Path, help="write weights, data sizes and the cross-validated figures here")
    parser.add_argument(
        "--sensor-thresholds", metavar="LAYOUTS",
        help="also give each of these beam layouts (comma-separated presets, or 'all') its own reject threshold for "
        "the weights (fitted here with --sim-sensors, else read from --weights-from): its budget by cross-validation "
        "over folds of its SynthCars sequences (--threshold-folds), written to --out as sensor_thresholds; "
        "reject_threshold becomes the largest (the sensor matching none)")
    parser.add_argument("--weights-from", type=Path,
                        help="with --sensor-thresholds and no --sim-sensors: the node YAML whose weights are used "
                        "(default: --base-config, else the shipped one); --out keeps its other lines")
    parser.add_argument("--threshold-folds", type=int, default=2,
                        help="with --sensor-thresholds: SynthCars sequences per cross-validation fold (2: a 40-frame "
                        "street of 20-frame sequences)")
    parser.add_argument(
        "--sensor-from", type=Path, metavar="SCANS",
        help="calibrate the threshold for YOUR LiDAR, read from a few of its scans (a bag / MCAP, KITTI, nuScenes or "
        "Argoverse 2 path): its beam model and height estimated as the node does, SynthCars simulated with it, the "
        "threshold for the weights of --weights-from (default: the shipped ones) set by cross-validation over its "
        "streets; no labelled frame needed. --out gets that threshold for every sensor")
    parser.add_argument("--sensor-scans", type=int, default=5, help="with --sensor-from: scans read (5)")
    parser.add_argument("--sensor-height", type=float,
                        help="with --sensor-from: the sensor's height above the ground in metres (default: read from "
                        "the scans)")
    parser.add_argument("--trees-out", type=Path, metavar="FILE",
                        help="boost trees from the weights of --weights-from (default: the shipped ones) on the "
                        "--sensor-thresholds layouts' simulated rows (and --real's frames), write them to FILE and "
                        "set each layout's threshold for weights plus trees; --out names FILE as trees")
    parser.add_argument("--tree-depth", type=int, default=3, help="with --trees-out: depth of each tree (3)")
    parser.add_argument("--tree-rounds", type=int, default=300, help="with --trees-out: boosting rounds (300)")
    parser.add_argument("--tree-rate", type=float, default=0.05, help="with --trees-out: shrinkage per tree (0.05)")
    parser.add_argument("--tree-monotone", action="store_true",
                        help="with --trees-out: hold each term whose physics gives a direction (density, free_space, "
                        "ground_gap, above, overlap, depth, corner, cover, through) to it in the trees")
    parser.add_argument("--real-layout", default="hdl64", choices=SENSOR_CHOICES[1:],
                        help="with --trees-out and --real: the layout whose threshold judges the held-out real "
                        "frames (hdl64: KITTI)")
    parser.add_argument("--rows-cache", type=Path,
                        help="keep each simulated set's measured rows here (keyed by the set and the measuring code): "
                        "rerunning on other weights then takes seconds")


def _budget(text: str) -> float | str:
    """``--max-lost``: a share in (0, 1), or ``cv`` (chosen by leave-one-sensor-out cross-validation)."""
    if text.strip().lower() == "cv":
        return "cv"
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--max-lost: a share such as 0.01, or 'cv'; got {text!r}") from None
    if not 0.0 <= value < 1.0:
        raise argparse.ArgumentTypeError(f"--max-lost: a share in [0, 1), got {value}")
    return value


def _synth_frames(root: Path, per_sequence: int):
    split = split_dir(root, "training")
    frames = []
    for seq in sorted(p.name for p in (split / "velodyne").iterdir() if p.is_dir()):
        frames += load_kitti(root, root / "detections" / "synthetic", seq, slice(0, per_sequence))
    return frames


def run(args: argparse.Namespace) -> int:
    if args.sim_sequences is None:
        args.sim_sequences = 8 if args.sensor_from else 2
    if args.sim_frames is None:
        args.sim_frames = 20 if args.sensor_from else 6
    if args.sim_seed is None:
        args.sim_seed = SENSOR_FROM_SEED if args.sensor_from else 11
    if args.sensor_from:
        from pcc_ros.cli.calibrate_sensors import run_sensor_from_scans

        return run_sensor_from_scans(args)
    if args.trees_out:
        from pcc_ros.cli.calibrate_trees import run_trees

        return run_trees(args)
    if args.sensor_thresholds and not args.sim_sensors:
        from pcc_ros.cli.calibrate_sensors import run_sensor_thresholds

        return run_sensor_thresholds(args)
    if args.sim_sensors or args.real is None:
        from pcc_ros.cli.calibrate_sensors import run_sensors

        return run_sensors(args)
    if args.real_detections is None:
        raise ConfigError("--real needs --real-detections (the real detector's results)")
    if args.max_lost == "cv":
        raise ConfigError("--max-lost cv holds out each simulated sensor in turn: it needs --sim-sensors (two or "
                          "more); the labelled-frame path takes a number, e.g. --max-lost 0.01")
    config = FilterConfig(rule="evidence", score_mapping=args.score_mapping, sensor=args.sensor)
    gt_classes = tuple(c.strip() for c in args.gt_classes.split(",") if c.strip())
    sequences = [q.strip() for q in args.real_sequence.split(",")] if args.real_sequence else [None]
    window = parse_frames(args.real_frames)
    real = [f for q in sequences for f in load_kitti(args.real, args.real_detections, q, window)]
    synth = _synth_frames(args.synth, args.synth_frames) if args.synth else []
    obj = []
    if args.object:
        obj = load_kitti(args.object, None)  # labelled cars become the true detections
    terms = parse_terms(args.terms, FIT_TERMS)
    result = calibrate(real, synth, obj, config, args.seed, gt_classes, max_lost=args.max_lost, l2=args.l2,
                       terms=terms)
    table = result["table"]
    counts = {s: {"true": int((~table.false[table.source == s]).sum()),
                  "false": int(table.false[table.source == s].sum())}
              for s in ("real", "synth", "object")}
    print("calibration rows:", json.dumps(counts))
    print("weights:", " ".join(f"w_{t}={w:+.4f}" for t, w in zip(TERMS, result["weights"])),
          f"w_bias={result['bias']:+.4f} reject_threshold={result['threshold']:.4f}")
    for name, fig in result["in_sample"].items():
        print(f"in-sample {name}: " + ", ".join(f"{k}={v:.3f}" if isinstance(v, float) else f"{k}={v}"
                                                for k, v in fig.items()))
    payload: dict[str, Any] = {
        "seed": args.seed, "terms": list(terms), "rows": counts, "bias": result["bias"],
        "weights": dict(zip(TERMS, result["weights"].tolist())), "threshold": result["threshold"],
        "in_sample": result["in_sample"], "max_lost": args.max_lost, "l2": args.l2,
        "real": str(args.real), "synth": str(args.synth), "object": str(args.object),
        "false_templates": {"count": len(result["templates"].range),
                            "range_median": float(np.median(result["templates"].range)),
                            "points_median": float(np.median(result["templates"].points)),
                            "score_median": float(np.median(result["templates"].score))},
    }
    if args.folds:
        cv = cross_validate(real, synth, obj, config, args.seed, gt_classes, args.folds, max_lost=args.max_lost,
                            l2=args.l2, terms=terms)
        payload["cross_validation"] = cv
        print(f"held-out ({args.folds} leave-frames-out folds over the real frames): " + ", ".join(
            f"{k}={v:.3f}" if isinstance(v, float) else f"{k}={v}" for k, v in cv["held_out"].items()))
    if args.out:
        header = (
            f"# calibrated: pcc calibrate-filter --real {args.real} --real-detections {args.real_detections}"
            f"{' --synth ' + str(args.synth) if args.synth else ''}"
            f"{' --object ' + str(args.object) if args.object else ''}"
            f" --score-mapping {args.score_mapping} --sensor {args.sensor} --seed {args.seed} --preset {args.preset}"
            f" --out {args.out}\n"
        )
        values = {"score_mapping": args.score_mapping, "sensor": args.sensor, **PRESETS[args.preset]}
        header += (
            f"# calibrated: preset {args.preset}, sensor {values['sensor']}, score_mapping {values['score_mapping']}\n"
        ) + PRESET_NOTES.get(args.preset, "")
        text = preset_yaml(args.base_config or default_config(), result["bias"], result["weights"], result["threshold"],
                           values, header)
        args.out.parent.mkdir(parents=True, exist_ok=True)
        write_text(args.out, text)
        log.info("wrote %s (score_mapping: %s%s)", args.out, values["score_mapping"],
                 "; these logits need score_mapping:=sigmoid / --score-mapping sigmoid where it is used"
                 if values["score_mapping"] != args.score_mapping else "")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        write_json(args.json, payload, indent=1, nonfinite_null=True)
    return 0
