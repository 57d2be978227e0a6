"""Does the evidence rule's scale hold across sensors? Variants of its terms, chosen by leave one sensor out.

One threshold serves every sensor only if a true car reads about the same ``p_false`` on each. This
measures every detection of the calibration sets (``pcc calibrate-filter --sim-root``, seed 11, and
the real KITTI frames, ``sensor: auto`` as the node runs), then for the shipped rule's terms and for
variants that read the beam model or the scan's ray counts (a covariate added, or ``free_space`` /
``density`` normalised), it prints:

* each sensor's own threshold for the budget (in sample) and its true cars' ``p_false`` by the
  returns in their box: which sensor's cars bind the one threshold; the rule refitted on each
  sensor alone;
* per variant, leave one sensor out at the budget chosen as ``--max-lost cv`` does
  (:func:`pcc_ros.workflows.filter_sensors.choose_budget`): each held-out sensor's true cars lost
  and false boxes removed per kind, and the mean per-kind removal against the shipped terms';
* with ``--heldout``, the rule fitted on every calibration row and judged on other seeds' sets
  (``data/synthcars_eval/<sensor>_s<seed>``, ``pcc synth --sequences 1 --frames 40``): look there
  only to accept or refuse what cross-validation chose.

An added covariate takes the column of ``top`` (weight 0 in the shipped rule), a replaced term its
own, so the fit, the budget choice and the folds are the calibration's own functions.

    PYTHONPATH=$PWD python scripts/filter_scale_check.py data/synthcars_sensors_8x20 \
        --heldout data/synthcars_eval --heldout-seeds 99,123 --variants shipped,free_space_core
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path

import numpy as np

from pcc_ros.pipeline.filter import TERMS
from pcc_ros.workflows.detection_eval import detection_truth, load_kitti
from pcc_ros.workflows.filter_calibration import predict, threshold_for
from pcc_ros.workflows.filter_sensors import (
    Rows,
    choose_budget,
    filled,
    fit_rows,
    leave_one_out,
    measuring_pipeline,
)

SHIPPED = ("density", "free_space", "ground_gap", "depth", "above", "overlap", "cover")
KINDS = ("confusion", "ghost", "far", "misplaced")
RAW = ("n_in", "n_pass", "n_stop", "n_rays", "n_occluded", "expected")
SPARE = "top"  # the column an added covariate takes


def measure(pipeline, frames, label: str, truth_of, kind_of, group_of) -> tuple[Rows, dict[str, np.ndarray]]:
    """Rows (every term) and the raw counts of ``frames``, the beam model estimated per group."""
    from dataclasses import replace

    from pcc_ros.pipeline.beam_model import BeamModel
    from pcc_ros.pipeline.filter import term_matrix

    pipeline.config = replace(pipeline.config, filter=replace(pipeline.config.filter, sensor="auto"))
    rows, raw, last = [], {k: [] for k in RAW}, None
    for f in frames:
        if group_of(f) != last:
            pipeline.beam_model, last = BeamModel("auto"), group_of(f)
        truth = truth_of(f)
        keep = truth >= 0
        boxes = f.dt.boxes[keep]
        if not len(boxes):
            continue
        t = pipeline.process(f.points, boxes).filter_terms
        n = len(boxes)
        rows.append(Rows(term_matrix({k: t.get(k, np.full(n, np.nan)) for k in TERMS}), truth[keep] == 0,
                         np.asarray(kind_of(f)[keep], dtype=object), np.full(n, label, dtype=object),
                         np.full(n, group_of(f), dtype=object)))
        for k in RAW:
            raw[k].append(np.asarray(t[k], dtype=np.float64))
    return Rows.concatenate(rows), {k: np.concatenate(v) for k, v in raw.items()}


def synth_set(pipeline, root: Path, layout: str):
    frames = []
    for seq in sorted(p.name for p in (root / "training" / "velodyne").iterdir() if p.is_dir()):
        frames += load_kitti(root, root / "detections" / "synthetic", seq)
    return measure(pipeline, frames, layout, lambda f: (f.kinds == "true").astype(np.int64), lambda f: f.kinds,
                   lambda f: f"{layout}:{f.name.split('/')[0]}")


def real_set(pipeline, root: Path, detections: Path):
    from dataclasses import replace

    pipeline.config = replace(pipeline.config, filter=replace(pipeline.config.filter, score_mapping="sigmoid"))
    frames = load_kitti(root, detections)
    index = {f.name: i for i, f in enumerate(frames)}
    gt = ("Car", "Van")
    return measure(pipeline, frames, "real", lambda f: detection_truth(f, gt, 0.3),
                   lambda f: np.where(detection_truth(f, gt, 0.3) == 1, "true", "real false"),
                   lambda f: f"real:{index[f.name] // 4}")


def _evidence(raw):
    visible = np.where(raw["n_rays"] > 0, 1.0 - raw["n_occluded"] / np.maximum(raw["n_rays"], 1.0), 1.0)
    return raw["expected"] * visible  # the returns a car there would give (the density's denominator)


#: Variant name -> (term replaced, or None to add a covariate; its values from (terms, raw counts)).
VARIANTS: dict[str, tuple[str | None, Callable]] = {
    "shipped": ("free_space", lambda x, r: x[:, TERMS.index("free_space")]),
    "log_expected": (None, lambda x, r: np.log1p(_evidence(r))),
    "log_expected_unhidden": (None, lambda x, r: np.log1p(r["expected"])),
    "free_space_expected": ("free_space", lambda x, r: x[:, TERMS.index("free_space")] / np.log(2 + _evidence(r))),
    "free_space_rays": ("free_space", lambda x, r: x[:, TERMS.index("free_space")]
                        / np.log(2 + r["n_rays"] - r["n_occluded"])),
    "free_space_core": ("free_space", lambda x, r: x[:, TERMS.index("free_space")]
                        / np.log(2 + r["n_pass"] + r["n_stop"])),
    "density_rays": ("density", lambda x, r: np.log((r["n_in"] + 1)
                                                    / (np.minimum(_evidence(r), r["n_rays"] - r["n_occluded"]) + 1))),
    "free_space_sensor": (None, lambda x, r: x[:, TERMS.index("free_space")] * r["sensor_level"]),
    "missing_beams": (None, lambda x, r: np.minimum(np.log((r["n_rays"] - r["n_occluded"] + 1)
                                                           / (_evidence(r) + 1)), 0.0)),
}


def sensor_level(sensor: np.ndarray) -> np.ndarray:
    """Per row, log(beams between -10 and +2 deg elevation per degree of azimuth) of its sensor's beam
    table (the real KITTI rows: the HDL-64E's), less the mean over the four simulated layouts: how much
    evidence the sensor gives a car near the horizon, one number a sensor."""
    from pcc_ros.geometry.beams import SENSOR_PRESETS

    def level(name: str) -> float:
        model = SENSOR_PRESETS[name]
        e = np.asarray(model.elevations_deg)
        return float(np.log(((e >= -10) & (e <= 2)).sum() / model.azimuth_resolution_deg))

    table = {s: level(s) for s in ("hdl64", "vlp16", "vlp32c", "os1_64")}
    centre = np.mean(list(table.values()))
    return np.array([table.get(s, table["hdl64"]) - centre for s in sensor])


def variant(rows: Rows, raw, name: str) -> tuple[Rows, tuple[str, ...]]:
    """``rows`` with the variant's column in place, and the terms it fits."""
    replaced, values = VARIANTS[name]
    raw = {**raw, "sensor_level": sensor_level(rows.sensor)}
    x = rows.x.copy()
    column = replaced or SPARE
    x[:, TERMS.index(column)] = values(rows.x, raw)
    terms = SHIPPED if replaced else (*SHIPPED, SPARE)
    return Rows(x, rows.false, rows.kind, rows.sensor, rows.group), terms


def per_kind(p: np.ndarray, reject: np.ndarray, rows: Rows) -> dict[str, float]:
    out = {"lost": float(reject[~rows.false].mean())}
    out.update({k: float(reject[rows.kind == k].mean()) for k in KINDS if (rows.kind == k).any()})
    return out


def table(title: str, figures: dict[str, dict[str, float]]) -> float:
    """Print one variant's per-sensor figures; return the mean per-kind removal."""
    print(f"{title}\n| sensor | true lost | {' | '.join(KINDS)} |\n|{' --- |' * (len(KINDS) + 2)}")
    for s, f in figures.items():
        print(f"| {s} | {f['lost']:.1%} | " + " | ".join(f"{f[k]:.1%}" if k in f else "none" for k in KINDS) + " |")
    mean = float(np.mean([f[k] for f in figures.values() for k in KINDS if k in f]))
    print(f"mean per-kind removal {mean:.2%}")
    return mean


def binding(rows: Rows, n_in: np.ndarray, budget: float, l2: float) -> None:
    """Each sensor's own in-sample threshold and its true cars' p_false by returns in the box."""
    bias, weights, threshold, mean = fit_rows(rows, SHIPPED, budget, l2)
    p = predict(bias, weights, filled(rows.x, mean))
    print(f"shipped terms, one threshold {threshold:.3f}; per sensor (own threshold at {budget:.2%}; 98 % quantile "
          "of the true cars' p_false by returns in the box 0 / 1-5 / 6-20 / 21+, and the share of cars in each)")
    for s in np.unique(rows.sensor):
        m = (rows.sensor == s) & ~rows.false
        own = threshold_for(p[rows.sensor == s], rows.false[rows.sensor == s], budget)
        parts = []
        for lo, hi in ((0, 0), (1, 5), (6, 20), (21, np.inf)):
            q = m & (n_in >= lo) & (n_in <= hi)
            parts.append(f"{np.quantile(p[q], 0.98):.2f} ({q.sum() / m.sum():.0%})" if q.any() else "none")
        print(f"  {s}: own threshold {own:.3f}; " + " / ".join(parts))
    print("refitted on each sensor alone: weights, and the intercept at a car's cover (bias + w_cover)")
    for s in np.unique(rows.sensor[rows.sensor != "real"]):
        b, w, _, _ = fit_rows(rows.subset(rows.sensor == s), SHIPPED, budget, l2)
        print(f"  {s}: " + ", ".join(f"{t} {w[TERMS.index(t)]:+.2f}" for t in SHIPPED)
              + f"; bias + w_cover {b + w[TERMS.index('cover')]:+.2f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("root", type=Path, help="calibration sets, <sensor>_s<seed> under it")
    parser.add_argument("--seed", type=int, default=11)
    parser.add_argument("--sensors", default="hdl64,vlp16,vlp32c,os1_64")
    parser.add_argument("--real", type=Path, default=Path("../shared/data/kitti_tracking"))
    parser.add_argument("--real-detections", type=Path,
                        default=Path("../shared/data/kitti_tracking/detections/pointrcnn"))
    parser.add_argument("--variants", default=",".join(VARIANTS))
    parser.add_argument("--heldout", type=Path, default=None, help="root of <sensor>_s<seed> held-out sets")
    parser.add_argument("--heldout-seeds", default="99,123")
    parser.add_argument("--l2", type=float, default=1e-2)
    args = parser.parse_args()
    sensors = args.sensors.split(",")
    pipeline = measuring_pipeline("trapcc", shape=False)
    parts = [synth_set(pipeline, args.root / f"{s}_s{args.seed}", s) for s in sensors]
    parts.append(real_set(pipeline, args.real, args.real_detections))
    rows = Rows.concatenate([r for r, _ in parts])
    raw = {k: np.concatenate([c[k] for _, c in parts]) for k in RAW}
    sim = rows.sensor != "real"
    binding(rows, raw["n_in"], choose_budget(rows, SHIPPED, args.l2, nested=False)["chosen"], args.l2)
    heldout = {}
    if args.heldout is not None:
        for seed in args.heldout_seeds.split(","):
            h = [synth_set(pipeline, args.heldout / f"{s}_s{seed}", s) for s in sensors]
            heldout[seed] = (Rows.concatenate([r for r, _ in h]),
                             {k: np.concatenate([c[k] for _, c in h]) for k in RAW})
    base = None
    for name in args.variants.split(","):
        vrows, terms = variant(rows, raw, name)
        budget = choose_budget(vrows, terms, args.l2, nested=False)["chosen"]
        folds = leave_one_out(vrows, vrows.sensor, terms, budget, args.l2, only=sim)["folds"]
        figures = {s: {"lost": f["true_lost"], **{k: v["removed"] for k, v in f["per_kind"].items()}}
                   for s, f in folds.items()}
        mean = table(f"\n## {name}: leave one sensor out, budget {budget:.2%}", figures)
        if base is None:
            base = (mean, figures)
        worst = min(f[k] - base[1][s][k] for s, f in figures.items() for k in KINDS if k in f)
        print(f"against {args.variants.split(',')[0]}: mean per-kind {100 * (mean - base[0]):+.2f} points, worst kind "
              f"{100 * worst:+.1f} points")
        bias, weights, threshold, mm = fit_rows(vrows, terms, budget, args.l2)
        for seed, (hrows, hraw) in heldout.items():
            hv, _ = variant(hrows, hraw, name)
            p = predict(bias, weights, filled(hv.x, mm))
            table(f"{name}, held-out seed {seed} (threshold {threshold:.3f})",
                  {s: per_kind(p[hv.sensor == s], p[hv.sensor == s] > threshold, hv.subset(hv.sensor == s))
                   for s in sensors})


if __name__ == "__main__":
    main()
