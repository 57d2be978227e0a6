"""``pcc demo``: the whole product on a SynthCars sequence, then on real KITTI frames.

1. Generate a small SynthCars world (a test-split sequence: its car shapes are never
   seen in training), convert it to an MCAP bag, replay it through the completion and
   filter pipeline exactly as the nodes run it.
2. Score the completions against the true car shapes (next to the ``input`` and
   ``mirror`` baselines) and the filter's decisions against which detections are truly
   false; print the tables and draw a PNG.
3. Repeat on the real KITTI tracking frames shipped beside the repository (real
   PointRCNN detections, logits -> sigmoid scores) when they are present.

Each half filters with the setting calibrated for its detector's score scale: the simulator's
detections with the shipped default (scan evidence calibrated across simulated sensors, no
score term), PointRCNN's with the KITTI preset (``config/detection_filter_kitti.yaml``, its
score term in PointRCNN's logits). Every printed table names its units and which way is better.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from pcc_ros import files
from pcc_ros.data.bag import read_frames
from pcc_ros.data.bag_writer import write_bag
from pcc_ros.data.kitti import KittiTracking
from pcc_ros.data.layouts import download_hint
from pcc_ros.errors import DataError
from pcc_ros.geometry.boxes import box_corners, iou_bev
from pcc_ros.geometry.canonical import to_canonical
from pcc_ros.metrics.suite import instance_metrics, to_metres
from pcc_ros.models import backend_names, get_backend
from pcc_ros.paths import shared_data_dir
from pcc_ros.pipeline.config import load_config, shipped_config_dir
from pcc_ros.pipeline.core import Pipeline
from pcc_ros.pipeline.filter import FilterConfig
from pcc_ros.plotting import label_boxes
from pcc_ros.runtime.bag_replay import replay_bag
from pcc_ros.tables import print_table
from pcc_ros.types import Boxes, class_mask

log = logging.getLogger(__name__)

VEHICLES = ("car", "van")
TRUE_IOU = 0.3  # BEV IoU with a labelled vehicle above which a detection counts as true
COMPLETION_METRICS = ("cd_l1", "precision", "coverage", "fscore")
#: The printed completion columns: metric -> header with its unit and which way is better.
COMPLETION_HEADERS = {"cd_l1": "CD-L1 m (lower better)", "precision": "precision m (lower better)",
                      "coverage": "coverage m (lower better)", "fscore": "F-score@1% (higher better)"}
#: The shipped filter presets of each half: the default (simulated sensors, no score term) and the
#: KITTI + PointRCNN preset (score term in PointRCNN's logits).
SYNTHCARS_FILTER = "detection_filter.yaml"
KITTI_FILTER = "detection_filter_kitti.yaml"


@dataclass
class DemoConfig:
    """What ``pcc demo`` is told (the CLI builds it from its flags, same names)."""

    out: Path = Path("out/demo")
    backend: str | None = None  # None: the shipped config's
    checkpoint: str | None = None  # None: the backend's shipped weights
    frames: int = 10  # SynthCars frames
    seed: int = 2026  # SynthCars seed
    kitti: Path | None = None  # None: ../shared/data/kitti_tracking
    baselines: str = "input,mirror"


@dataclass
class FilterTally:
    """Detections by truth (true / false) and decision (kept / rejected)."""

    counts: dict[str, int] = field(default_factory=lambda: dict.fromkeys(
        ("true_kept", "true_rejected", "false_kept", "false_rejected"), 0))

    def add(self, is_true: np.ndarray, rejected: np.ndarray) -> None:
        self.counts["true_kept"] += int((is_true & ~rejected).sum())
        self.counts["true_rejected"] += int((is_true & rejected).sum())
        self.counts["false_kept"] += int((~is_true & ~rejected).sum())
        self.counts["false_rejected"] += int((~is_true & rejected).sum())

    def table_row(self, detections: str) -> dict[str, object]:
        """The printed row: counts, and the share of kept detections that are true (higher is better)."""
        s = self.summary()
        return {"detections": detections, "true kept": s["true_kept"],
                "true rejected (fewer better)": s["true_rejected"], "false kept (fewer better)": s["false_kept"],
                "false rejected": s["false_rejected"],
                "true share of kept: before": round(s["precision_before"], 3),
                "after (higher better)": round(s["precision_after"], 3)}

    def summary(self) -> dict[str, float]:
        c = self.counts
        total = sum(c.values())
        true = c["true_kept"] + c["true_rejected"]
        kept = c["true_kept"] + c["false_kept"]
        return {
            **c,
            "precision_before": true / total if total else float("nan"),
            "precision_after": c["true_kept"] / kept if kept else float("nan"),
            "true_retained": c["true_kept"] / true if true else float("nan"),
            "false_removed": c["false_rejected"] / (total - true) if total > true else float("nan"),
        }


def truly_vehicle(detections: Boxes, truth: Boxes | None) -> np.ndarray:
    """Which detections overlap a labelled Car / Van (BEV IoU >= TRUE_IOU)."""
    if truth is None or len(truth) == 0 or len(detections) == 0:
        return np.zeros(len(detections), dtype=bool)
    vehicles = truth[class_mask(truth.label, VEHICLES) & truth.valid_mask()]
    if len(vehicles) == 0:
        return np.zeros(len(detections), dtype=bool)
    return iou_bev(detections, vehicles).max(axis=1) >= TRUE_IOU


def _replay(bag: Path, out_bag: Path | None, config, frames_by_stamp: dict, on_frame,
            with_filter: bool = True) -> object:
    """Replay ``bag`` through the filter node (``with_filter``) or the completion node alone."""
    pipeline = Pipeline(config)
    return replay_bag(
        bag, out_bag, pipeline, with_filter=with_filter, force=True, progress=False,
        on_result=lambda result, cloud, dets: on_frame(result, frames_by_stamp[result.stamp_ns]),
    )


def completion_scores(result, frame, shapes_root: Path) -> list[dict[str, float]]:
    """Metrics (metres) of each completed detection that matches a labelled car with a true shape."""
    from pcc_ros.data.synthetic import load_shape

    truth = frame.ground_truth
    if truth is None or len(truth) == 0 or len(result.completed_index) == 0:
        return []
    truth = truth[truth.valid_mask()]
    iou = iou_bev(result.detections[result.completed_index], truth)
    rows = []
    for k, det in enumerate(result.completed_index):
        j = int(np.argmax(iou[k]))
        if iou[k, j] < 0.5:
            continue
        shape = load_shape(shapes_root, frame.sequence, truth.track_id[j])
        if shape is None:
            continue
        length = float(truth.size[j, 0])
        completed = result.completion_points(det)
        pred = to_canonical(completed, truth.center[j], truth.yaw[j], length)
        metrics = instance_metrics(pred, shape, length=length, with_emd=False)
        rows.append({m: float(to_metres(m, metrics[m], length)) for m in COMPLETION_METRICS})
    return rows


def run_synthcars(opts: DemoConfig, config) -> dict:
    from pcc_ros.data.synthetic import generate

    root = opts.out / "synthcars"
    meta = generate(root, sequences=2, frames=opts.frames, seed=opts.seed, test_fraction=0.5, progress=True)
    sequence = meta["splits"]["test"][0]
    bag = opts.out / "synthcars_test"  # a rosbag2 folder, like the replayed ones beside it
    frames = KittiTracking(root / "training").frames(sequence, detections_dir=root / "detections" / "synthetic")
    write_bag(frames, bag, force=True, progress=False)
    frames_by_stamp = {f.stamp_ns: f for f in read_frames(bag)}
    for f in frames_by_stamp.values():
        f.sequence = sequence

    baselines = backend_names(opts.baselines, "--baselines", empty_ok=True)
    backends = [config.backend] + [b for b in baselines if b != config.backend]
    completion_rows, tally, pictures = [], FilterTally(), {}
    for backend in backends:
        scores: list[dict[str, float]] = []
        primary = backend == config.backend

        def on_frame(result, frame, scores=scores, primary=primary):
            scores.extend(completion_scores(result, frame, root))
            if primary:
                tally.add(truly_vehicle(result.detections, frame.ground_truth), ~result.keep)
                pictures[result.stamp_ns] = (result, frame)

        cfg = config if primary else replace(config, backend=backend, checkpoint="")
        # a baseline is only scored on its completions: the completion node runs it, not the filter
        _replay(bag, opts.out / "synthcars_replayed" if primary else None, cfg, frames_by_stamp, on_frame,
                with_filter=primary)
        mean = {m: float(np.mean([s[m] for s in scores])) for m in COMPLETION_METRICS}
        completion_rows.append({"backend": backend, "instances": len(scores), **mean})

    print_table("SynthCars completion vs true shapes (metres, lower is better; F-score@1% 0-1, higher is better)",
                [{"backend": r["backend"], "cars": r["instances"], **{COMPLETION_HEADERS[m]: round(r[m], 3)
                                                                        for m in COMPLETION_METRICS}}
                 for r in completion_rows])
    filter_summary = tally.summary()
    print_table(f"SynthCars detection filter, config/{SYNTHCARS_FILTER} (true = BEV IoU >= 0.3 with a labelled car)",
                [tally.table_row("simulated detector")])
    stamp = sorted(pictures)[len(pictures) // 2]
    png = opts.out / "synthcars_demo.png"
    plot_frame(*pictures[stamp], png, f"SynthCars test sequence {sequence}, backend {config.backend}")
    return {"completion": completion_rows, "filter": filter_summary, "filter_config": f"config/{SYNTHCARS_FILTER}",
            "png": str(png)}


def run_kitti(opts: DemoConfig, config) -> dict | None:
    root = opts.kitti or shared_data_dir() / "kitti_tracking"
    if not (root / "training").is_dir():
        print(f"\nReal KITTI half skipped: no KITTI tracking data at {root}. Get it, then `pcc demo --kitti ROOT`: "
              f"{download_hint(('KITTI tracking',))}")
        return None
    detections = root / "detections" / "pointrcnn"
    bag = opts.out / "kitti_0000"
    frames = KittiTracking(root / "training").frames("0000", detections_dir=detections if detections.is_dir() else None)
    write_bag(frames, bag, force=True, progress=False)
    frames_by_stamp = {f.stamp_ns: f for f in read_frames(bag)}
    # PointRCNN's preset (its score term is in PointRCNN's logits: map them explicitly)
    preset = shipped_config_dir() / KITTI_FILTER
    if preset.is_file():
        config = replace(config, filter=load_config(preset, with_filter=True)[0].filter)
    setting = f"config/{KITTI_FILTER if preset.is_file() else SYNTHCARS_FILTER}, score_mapping sigmoid"
    config = replace(config, filter=replace(config.filter, score_mapping="sigmoid"))
    assert isinstance(config.filter, FilterConfig)
    tally, pictures = FilterTally(), {}

    def on_frame(result, frame):
        tally.add(truly_vehicle(result.detections, frame.ground_truth), ~result.keep)
        pictures[result.stamp_ns] = (result, frame)

    _replay(bag, opts.out / "kitti_replayed", config, frames_by_stamp, on_frame)
    summary = tally.summary()
    print_table(f"Real KITTI 0000 detection filter, {setting} (true = BEV IoU >= 0.3 with a label)",
                [tally.table_row("PointRCNN")])
    stamp = sorted(pictures)[len(pictures) // 2]
    png = opts.out / "kitti_demo.png"
    plot_frame(*pictures[stamp], png, f"KITTI tracking 0000 (real scan), backend {config.backend}")
    return {"filter": summary, "filter_config": setting, "png": str(png)}


def plot_frame(result, frame, path: Path, title: str) -> None:
    """BEV of one frame: scan, completed cars, boxes coloured by truth and filter decision."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(11, 9), dpi=110)  # the saved dpi: labels are placed in display space
    pts = frame.points
    near = (np.abs(pts[:, 0]) < 50) & (np.abs(pts[:, 1]) < 40) & (pts[:, 2] > -1.5)
    ax.scatter(pts[near, 0], pts[near, 1], s=0.2, c="0.7", linewidths=0, label="scan (ground removed)")
    done = result.completed_instance >= 0
    # Completions in colours the box outlines do not use (green / orange / purple / red / grey mean decisions).
    palette = np.array(["tab:blue", "tab:brown", "tab:pink", "tab:olive", "tab:cyan"])
    ax.scatter(result.completed_points[done, 0], result.completed_points[done, 1], s=0.5,
               c=palette[result.completed_instance[done] % len(palette)], linewidths=0)
    truth = truly_vehicle(result.detections, frame.ground_truth)
    styles = {
        (True, "kept"): ("tab:green", "-", "true, kept"),
        (True, "rejected"): ("tab:orange", "-", "true, rejected"),
        (False, "kept"): ("tab:purple", "--", "false, kept"),
        (False, "rejected"): ("tab:red", "--", "false, rejected"),
        (True, "skipped"): ("0.35", ":", "not judged (skipped)"),
        (False, "skipped"): ("0.35", ":", "not judged (skipped)"),
        (True, "unjudged"): ("goldenrod", ":", "could not be judged"),
        (False, "unjudged"): ("goldenrod", ":", "could not be judged"),
    }
    corners = box_corners(result.detections)[:, [0, 1, 2, 3, 0], :2] if len(result.detections) else []
    # The number the filter decided on: p_false (evidence rule) or the mismatch (trapcc rule).
    judged = result.filter_score if result.filter_score is not None else result.mismatch
    used, texts, colors = set(), [], []
    for i, c in enumerate(corners):
        key = (bool(truth[i]), str(result.status[i]))
        color, ls, name = styles[key]
        ax.plot(c[:, 0], c[:, 1], color=color, ls=ls, lw=1.6, zorder=4, label=None if name in used else name)
        used.add(name)
        texts.append(f"{judged[i]:.2f}" if np.isfinite(judged[i]) else None)
        colors.append(color)
    ax.plot([0], [0], marker=">", color="k", ms=10)
    ax.set_aspect("equal")
    ax.set_xlim(-50, 50)
    ax.set_ylim(-40, 40)
    ax.set_xlabel("x forward (m)")
    ax.set_ylabel("y left (m)")
    ax.set_title(f"{title}\ncoloured points: completions; numbers: the filter's score (p_false, or mismatch)")
    ax.legend(loc="upper right", fontsize=8, markerscale=8)
    label_boxes(ax, np.asarray(corners), texts, colors)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)


def demo(opts: DemoConfig) -> dict:
    """The demo as ``opts`` says: SynthCars, then real KITTI; writes ``demo.json`` and the PNGs, returns the results."""
    if opts.kitti is not None and not (Path(opts.kitti) / "training").is_dir():  # named: an error, not half a demo
        raise DataError(f"{opts.kitti}: no KITTI tracking data here (no {Path(opts.kitti) / 'training'}) — pass "
                        "--kitti the folder holding training/velodyne/0000", hint=download_hint(("KITTI tracking",)))
    config, _ = load_config(None, with_filter=True, backend=opts.backend, checkpoint=opts.checkpoint)
    get_backend(config.backend)  # a misspelt --backend / --baselines is said before SynthCars is generated
    backend_names(opts.baselines, "--baselines", empty_ok=True)  # "": none
    opts.out.mkdir(parents=True, exist_ok=True)
    results = {"backend": config.backend, "synthcars": run_synthcars(opts, config), "kitti": run_kitti(opts, config)}
    files.write_json(opts.out / "demo.json", results, indent=2)
    return results
