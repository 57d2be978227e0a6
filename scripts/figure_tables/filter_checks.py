"""docs/filter.md's checks of the detection filter: ``pcc eval detections --json`` on the real and
simulated frames (nuScenes, KITTI + PointRCNN, SynthCars per sensor) and ``pcc calibrate-filter
--json`` (the shipped default across sensors, the KITTI preset), stored under ``docs/results/``."""

from __future__ import annotations

from typing import Any

from .base import Figure, one, pct, table

#: The simulated sensors of the per-kind check, in the docs' column order.
SENSORS = ("hdl64", "vlp16", "vlp32c", "os1_64")
#: Beam layouts SynthCars simulates that the shipped rule's calibration never saw.
UNSEEN_SENSORS = ("hdl32", "vlp32c_x2", "os1_128", "pandar64")
#: The false-positive kinds of SynthCars' simulated detector, and the real frames' false detections.
KINDS = ("confusion", "ghost", "far", "misplaced")
#: The trapcc rule's completion backends, as the eval-on-KITTI table lists them.
TRAPCC_BACKENDS = ("pointpncnet", "trapcc", "aml")
BUDGET = "false_removed_at_0.02_lost"


def _synth(sensor: str, seed: str = "") -> str:
    """The stored check of a held-out simulated sensor: seed 99 unsuffixed, another seed as ``-s<seed>``."""
    return f"filter-synth-{sensor}" + (f"-s{seed}" if seed else "")


def _share(count: int, total: int) -> str:
    return f"{pct(count / total)} ({count} / {total})" if total else "-"


def _by_sensor(results: dict[str, dict[str, Any]], value) -> str:
    return " / ".join(value(results[_synth(s)]) for s in SENSORS)


# --------------------------------------------------------------------------- the nuScenes check


def _nuscenes_summary(d: dict[str, Any]) -> str:
    c = d["configured"]
    cars = d["true"]
    lost = [round(v["true_lost"] * cars) for v in d["by_score"].values()]
    scores = "-".join(str(s) for s in (min(d["by_score"]), max(d["by_score"])))
    seen = "; ".join(f"its car with {car['returns']} returns {car['status']} (p_false {car['p_false']:.3f})"
                     for car in d["well_seen_cars"])
    return (f"{max(lost)} / {cars} cars lost at any score {scores}; {seen}; non-vehicle boxes removed "
            f"**{pct(c['non_vehicle_removed'])}** ({pct(c['non_vehicle_removed_without_overlap'])} without the "
            f"`overlap` term), free ground {pct(c['free_ground_removed'])}; ranked by p_false "
            f"{pct(d['methods']['filter'][BUDGET])} of all false boxes go at <= 2 % cars lost (points in the box: "
            f"{pct(d['methods']['points-in-box'][BUDGET])})")


def render_nuscenes_kitti_preset(d: dict[str, Any]) -> list[str]:
    """docs/filter.md: the KITTI preset, as shipped, on the nuScenes frame (a sensor and a score
    scale it was not calibrated for)."""
    lost = ", ".join(f"{round(v['true_lost'] * d['true'])} / {d['true']} at score {s}"
                     for s, v in sorted(d["by_score"].items()))
    seen = "; ".join(f"the car with {car['returns']} returns {car['status']} (p_false {car['p_false']:.3f})"
                     for car in d["well_seen_cars"])
    return [f"The KITTI preset as shipped (`config/detection_filter_kitti.yaml`: HDL-64E beam table, score term "
            f"fitted on PointRCNN's logits) on this frame rejects {lost} of the cars; {seen}."]



# --------------------------------------------------------------------------- SynthCars per kind


# --------------------------------------------------------------------------- what the shipped rule was checked on


def _held_out(d: dict[str, Any]) -> str:
    """Held-out figures of either calibration JSON (across sensors: ``false_removed``; the KITTI
    path: ``false_removed_at_fold_threshold``)."""
    removed = d.get("false_removed", d.get("false_removed_at_fold_threshold"))
    lost = d.get("true_lost", d.get("true_lost_at_fold_threshold"))
    return (f"{pct(removed)} removed, {round(lost * d['true'])} / {d['true']} lost at the fold thresholds; "
            f"AUC {d['auc_false_above_true']:.3f} ({pct(d[BUDGET + '_best'])} at the best threshold for <= 2 % lost)")


def render_checked_on(results: dict[str, dict[str, Any]]) -> list[str]:
    """The shipped rule on every set it was checked on: one row per data set."""
    nus, trees, kitti = results["filter-nuscenes"], results["filter-trees"], results["calibrate-kitti"]

    def synth(field: str) -> str:
        return _by_sensor(results, lambda d: pct(d["per_kind"]["configured"][field]))

    def kind(name: str) -> str:
        return _by_sensor(results, lambda d: pct(d["per_kind"]["configured"]["per_group_removed"].get(name, 0)))

    s = results[_synth(SENSORS[0])]
    rows = [
        [f"nuScenes, {nus['frames']} key frame (real)", "HDL-32E, ring field",
         f"none: boxes on the annotations, every score {nus['score']}", _nuscenes_summary(nus)],
        [f"SynthCars, held-out seed 99, {s['frames']} frames per sensor", " / ".join(SENSORS) + " (simulated)",
         "simulated, four false-positive kinds",
         f"true lost {synth('true_lost')}; false removed {synth('false_removed')} (points in the box at <= 2 % "
         f"lost: {_by_sensor(results, lambda d: pct(d['per_kind']['methods']['points-in-box'][BUDGET]))}); "
         f"confusions {kind('confusion')}; misplaced {kind('misplaced')}"],
        [f"KITTI tracking 0000, {sum(len(f['frames']) for f in kitti['cross_validation']['folds'])} frames (real)",
         "HDL-64E",
         "PointRCNN", f"held out by blocks of 4 frames (trees boosted without the block): "
                      f"{_held_out(trees['real_frames'])}"],
        ["the same, with the KITTI preset's rule (`config/detection_filter_kitti.yaml`'s command, score term "
         "included)", "HDL-64E", "PointRCNN", f"held out ({len(kitti['cross_validation']['folds'])} folds): "
         f"{_held_out(kitti['cross_validation']['held_out'])}"],
    ]
    return table(["data", "sensor (beam model `auto`)", "detector", "result, shipped default"], rows)


# --------------------------------------------------------------------------- calibration


def _weights(d: dict[str, Any]) -> str:
    named = ", ".join(f"{term} {w:+.3f}" for term, w in d["weights"].items() if w)
    zero = ", ".join(term for term, w in d["weights"].items() if not w)
    return f"bias {d['bias']:+.3f}, {named}" + (f"; 0: {zero}" if zero else "")


def render_calibration_kitti(results: dict[str, dict[str, Any]]) -> list[str]:
    """The KITTI + PointRCNN calibration: rows, weights, threshold, in-sample and held-out figures,
    and the same fitted on the physics terms alone."""
    d, physics = results["calibrate-kitti"], results["calibrate-kitti-physics"]
    names = {"real": "real", "synth": "SynthCars", "object": "KITTI object"}
    held, held_physics = d["cross_validation"]["held_out"], physics["cross_validation"]["held_out"]

    def held_out(h: dict[str, Any]) -> str:
        lost = h["true_lost_at_fold_threshold"]
        return (f"{pct(h['false_removed_at_fold_threshold'])} of false removed, {pct(lost)} "
                f"({round(lost * h['true'])} of {h['true']}) true lost at each fold's own "
                f"threshold; at the best threshold {pct(h[BUDGET + '_best'])} removed at <= 2 % lost; "
                f"P(false scores above true) {h['auc_false_above_true']:.3f}")

    in_sample = " / ".join(names[k] for k in d["in_sample"])
    rows = [
        ["rows", "; ".join(f"{names[k]} {v['true']:,} true / {v['false']} false" for k, v in d["rows"].items())],
        ["weights (per unit of each term)", _weights(d)],
        ["`reject_threshold` (loses at most `--max-lost` "
         f"{pct(d['max_lost'])} of the true detections of each source: real, SynthCars, object)",
         f"{d['threshold']:.3f}"],
        [f"in-sample: {in_sample}",
         " / ".join(pct(v["false_removed_at_threshold"]) for v in d["in_sample"].values()) + " of false removed at "
         + " / ".join(pct(v["true_lost_at_threshold"]) for v in d["in_sample"].values()) + " of true lost"],
        [f"**held-out real ({len(d['cross_validation']['folds'])} folds)**", held_out(held)],
        [f"physics terms only (`--terms {','.join(physics['terms'])}`)", f"held-out real: {held_out(held_physics)}; "
         f"SynthCars in-sample P(false above true) {physics['in_sample']['synth']['auc_false_above_true']:.3f}"],
    ]
    return table(["", "value"], rows)


def _cv(d: dict[str, Any]) -> str:
    return f"{pct(d['false_removed'])} at {pct(d['true_lost'])} lost, AUC {d['auc_false_above_true']:.3f}"


def render_term_auc(results: dict[str, dict[str, Any]]) -> list[str]:
    """Each measured term alone: AUC of a kind's boxes scoring above the true cars, on the calibration
    rows / on held-out rows of seed 99 (the real frames only in the first)."""
    d, s99 = results["filter-calibration"], results["calibrate-s99"]
    real = "real false" in next(iter(d["term_auc"].values()))

    terms = [t for t in d["term_auc"] if t not in ("density", "free_space", "ground_gap", "score", "mismatch")]

    def row(term: str) -> list[str]:
        label = f"(`{term}`, for scale)" if term == "free_space" else f"`{term}`"
        held = s99["term_auc"].get(term)  # a term newer than the held-out run: "-"
        cells = [f"{d['term_auc'][term][k]:.3f} / " + (f"{held[k]:.3f}" if held else "-") for k in KINDS]
        return [label, *cells, *([f"{d['term_auc'][term]['real false']:.3f}"] if real else [])]

    header = ["term (AUC: 0.5 chance, 1 every false box above every true car)", *KINDS,
              *(["KITTI false"] if real else [])]
    return table(header, [row(term) for term in (*terms, "free_space")])


# --------------------------------------------------------------------------- pcc eval detections on KITTI and SynthCars


def _configured(d: dict[str, Any]) -> str:
    s = d["shipped_threshold"]
    return (f"{pct(s['false_removed_share'])} ({s['false_removed']} / {s['false_removed'] + s['false_kept']}), "
            f"{s['true_lost']} true lost; precision {s['precision_before']:.3f} -> {s['precision_after']:.3f}")


def render_eval_kitti(results: dict[str, dict[str, Any]]) -> list[str]:
    """``pcc eval detections`` on the real KITTI frames with PointRCNN: AP before / after the filter,
    the operating points against the trivial baselines, the TraPCC rule per backend, the cost."""
    d = results["filter-kitti"]
    ap = table([f"KITTI AP_R40, {' + '.join(d['gt_classes'])}, moderate (higher is better)", "before", "after"],
               [[metric.replace("3d", "3D").replace("bev", "BEV").replace("@", " @ "),
                 f"{d['ap_before'][metric]['moderate']:.2f}", f"{d['ap_after'][metric]['moderate']:.2f}"]
                for metric in ("3d@0.7", "3d@0.5", "bev@0.7", "bev@0.5")])
    ops = d["operating_points"]
    trapcc = [results[f"filter-kitti-trapcc-{b}"] for b in TRAPCC_BACKENDS]
    rows = [
        ["**filter, configured threshold**", f"**{_configured(d)}**"],
        ["filter, best threshold", pct(ops["filter"][BUDGET])],
        [f"points in box, best threshold (<= {ops['points-in-box']['threshold']:.0f} points)",
         pct(ops["points-in-box"][BUDGET])],
        ["detector score, best threshold", pct(ops["detector score"][BUDGET])],
        [f"TraPCC rule (`--rule trapcc --backend B`), B = {' / '.join(TRAPCC_BACKENDS)}",
         " / ".join(pct(t["operating_points"]["filter"][BUDGET]) for t in trapcc) + " (P(false above true) "
         + " / ".join(f"{t['operating_points']['filter']['auc_false_above_true']:.2f}" for t in trapcc) + ")"],
    ]
    cost = (f"Filter cost, as the command prints it: {d['filter_ms_mean']:.1f} ms per frame against "
            f"{d['complete_ms_mean']:.1f} ms for the configured completion stage (means over the "
            f"{d['frames']} frames, on a machine whose load this command does not record: the timed figures are "
            "`pcc bench filter`'s, below).")
    return [*ap, "", *table([f"{d['false']} false / {d['true']} true detections", "false removed at <= 2 % true lost"],
                            rows), "", cost]


def render_eval_synthcars(results: dict[str, dict[str, Any]]) -> list[str]:
    """A SynthCars sequence the calibration never saw: the KITTI preset against a rule calibrated for the
    simulated detector, with the trivial baselines."""
    preset, calibrated = results["filter-synthcars-kitti-preset"], results["filter-synthcars-calibrated"]

    def ap(d: dict[str, Any]) -> str:
        return f"{d['ap_before']['3d@0.7']['moderate']:.2f} -> {d['ap_after']['3d@0.7']['moderate']:.2f}"

    def configured(d: dict[str, Any]) -> str:
        s = d["shipped_threshold"]
        return f"{pct(s['false_removed_share'])} removed, {pct(s['true_lost_share'])} true lost"

    ops = preset["operating_points"]
    rows = [
        ["KITTI preset (PointRCNN scale)", pct(ops["filter"][BUDGET]), configured(preset), ap(preset)],
        ["calibrated for this detector", pct(calibrated["operating_points"]["filter"][BUDGET]),
         configured(calibrated), ap(calibrated)],
        ["points in box", pct(ops["points-in-box"][BUDGET]), "", ""],
        ["detector score", pct(ops["detector score"][BUDGET]), "", ""],
    ]
    header = [f"SynthCars seed 99, {preset['true']} true / {preset['false']} false",
              "false removed at <= 2 % lost, best threshold (higher is better)", "configured threshold",
              "AP40 3D @ 0.7 moderate, before -> after"]
    return table(header, rows)


def render_sensor_from_scans(d: dict[str, Any]) -> list[str]:
    """A sensor no preset describes: the shipped file (its fallback threshold) against the file
    ``pcc calibrate-filter --sensor-from`` writes from the sensor's scans, on held-out streets."""
    sensor, est = d["sensor"], d["calibration"]["sensor"]
    fit = d["calibration"]["threshold"]
    rows = []
    for seed, files in d["streets"].items():
        for name, r in files.items():
            count, removed = r["per_kind_count"], r["per_kind_removed"]
            kinds = ", ".join(f"{k} {pct(removed[k])} ({count[k]})" for k in KINDS if k in count)
            total = sum(count.values())
            rows.append([f"seed {seed}", name, f"{r['threshold']['threshold']:.3f}",
                         _share(r["true_lost_count"], r["true"]),
                         _share(round(sum(count[k] * removed[k] for k in count)), total), kinds])
    header = ["street (1 x 40 frames)", "file", "threshold in force", "true cars lost", "false boxes removed",
              "per kind"]
    return [f"Sensor: {sensor['beams']} beams {min(sensor['elevations_deg']):+g} to {max(sensor['elevations_deg']):+g}"
            f" deg, {sensor['azimuth_step_deg']:g} deg step, {sensor['mount_height_m']:g} m high; read from "
            f"{est['agreeing']} of {est['scans']} scans as {est['beams']} beams, "
            f"{min(est['elevations_deg']):+.2f} to {max(est['elevations_deg']):+.2f} deg, "
            f"{est['azimuth_step_deg']:.3f} deg step, {est['mount_height_m']:.2f} m high (matching preset: "
            f"{est['matching_preset'] or 'none'}); calibrated threshold {fit['threshold']:.3f} (budget "
            f"{pct(fit['budget'], 2)}, worst held-out simulated fold {pct(fit['cv_worst_fold'])}).", "",
            *table(header, rows)]


# ---------------------------------------------------- the shipped rule's checks (per kind, nuScenes, calibration)


def _pct(value: float | None) -> str:
    return "-" if value is None else pct(value)


def render_filter_synth(results: dict[str, dict[str, Any]], seed: str = "",
                        sensors: tuple[str, ...] = SENSORS) -> list[str]:
    """Per false-positive kind and held-out simulated sensor: removed at the configured threshold
    (the filter and points-in-box at their best threshold for <= 2 % lost), and the true cars lost."""
    kinds = {s: results[_synth(s, seed)]["per_kind"] for s in sensors}

    def cell(k: dict[str, Any], kind: str) -> str:
        n = k["configured"]["per_group_count"].get(kind)
        if not n:
            return "none"
        best, pib = (k["methods"][m]["per_group_removed"][kind] for m in ("filter", "points-in-box"))
        return f"{_pct(k['configured']['per_group_removed'][kind])} ({_pct(best)} / {_pct(pib)}) of {n}"

    rows = [[kind, *(cell(kinds[s], kind) for s in sensors)] for kind in KINDS]
    rows.append(["all false", *(f"{_pct(k['configured']['false_removed'])} "
                                f"({_pct(k['methods']['filter']['false_removed_at_0.02_lost'])} / "
                                f"{_pct(k['methods']['points-in-box']['false_removed_at_0.02_lost'])})"
                                for k in kinds.values())])
    rows.append(["**true cars lost** (by kind label)", *(f"**{k['configured']['true_lost_count']} / {k['true']}** "
                                                          f"({_pct(k['configured']['true_lost'])})"
                                                          for k in kinds.values())])
    return table(["kind: configured (filter at the budget / points-in-box)", *sensors], rows)


def render_filter_nuscenes(d: dict[str, Any]) -> list[str]:
    """The nuScenes check per group: removed at the configured threshold, and by the filter and by
    points-in-box at their best threshold for <= 2 % of the cars lost; then the headline figures."""
    conf, methods = d["configured"], d["methods"]
    rows = [[g, conf["per_group_count"][g], _pct(conf["per_group_removed"][g]),
             _pct(methods["filter"]["per_group_removed"][g]), _pct(methods["points-in-box"]["per_group_removed"][g])]
            for g in sorted(conf["per_group_count"])]
    cars = "; ".join(f"car with {c['returns']} returns at {c['range_m']} m: p_false {c['p_false']:.3f}, {c['status']}"
                     for c in d["well_seen_cars"])
    return [*table(["false group", "boxes", "configured", "filter, best for <= 2 % lost", "points-in-box, same"],
                   rows), "",
            f"Non-vehicle boxes removed at the configured threshold: **{_pct(conf['non_vehicle_removed'])}** "
            f"({_pct(conf.get('non_vehicle_removed_without_overlap'))} without the `overlap` term); free ground "
            f"{_pct(conf['free_ground_removed'])}; cars lost {conf['true_lost_count']} / {d['true']}; {cars}."]


def render_filter_calibration(results: dict[str, dict[str, Any]]) -> list[str]:
    """``pcc calibrate-filter --sim-sensors``: weights, leave-one-sensor-out and leave-one-sequence-out
    figures at each fold's own threshold, the ablation; beside it the same fit offered the shape term."""
    d, shape = results["filter-calibration"], results["filter-calibration-shape"]

    def weights(r: dict[str, Any]) -> str:
        return ", ".join(f"{t} {w:+.2f}" for t, w in r["weights"].items() if w) + f"; bias {r['bias']:+.2f}, " \
            f"threshold {r['threshold']:.3f}"

    def folds(r: dict[str, Any]) -> str:
        return "; ".join(f"{s}: {_pct(f['false_removed'])} removed at {_pct(f['true_lost'])} lost, confusions "
                         f"{_pct(f['per_kind'].get('confusion', {}).get('removed'))}"
                         for s, f in r["cv_by_sensor"]["folds"].items())

    def kinds(r: dict[str, Any]) -> str:
        p = r["cv_by_sequence"]["pooled"]
        return ", ".join(f"{k} {_pct(v['removed'])}" for k, v in p["per_kind"].items()) + \
            f" ({_pct(p['true_lost'])} true lost; AUC {p['auc_false_above_true']:.3f})"

    def share(b: float) -> str:  # a budget of the grid (0.75 %, not 0.8 %)
        return f"{b * 100:g} %"

    def budget(r: dict[str, Any]) -> str:
        sel = r.get("budget_selection")
        if sel is None:
            return f"{share(r.get('max_lost', 0.01))} of each sensor's true cars (set by hand)"
        nested = "; ".join(f"{s} {_pct(n['true_lost'])} lost at {share(n['budget'])}" for s, n in sel["nested"].items()
                           if n["budget"] is not None)
        return (f"**{share(sel['chosen'])}** of each sensor's true cars: the largest budget whose held-out sensors "
                f"each lose <= {_pct(sel['target_lost'])} (worst held-out loss at " + ", ".join(
                    f"{share(b)}: {_pct(w)}" for b, w in zip(sel["grid"], sel["worst_held_out_lost"]))
                + f"); each sensor also held out of the choice: {nested}")

    def per_layout(r: dict[str, Any]) -> str:
        st = r.get("sensor_thresholds")
        if not st:
            return "none: `reject_threshold` for every sensor"
        return ", ".join(f"{name} {v['threshold']:.3f} ({share(v['budget'])})" for name, v in st["layouts"].items()) \
            + f"; matching no preset: {st['fallback']:.3f}"

    m = shape["mismatch"]
    rows = [["weights", weights(d), weights(shape)],
            ["per-layout thresholds (`sensor_thresholds`; budget)", per_layout(d), per_layout(shape)],
            ["loss budget (`--max-lost`)", budget(d), budget(shape)],
            ["held-out sensor (fold threshold)", folds(d), folds(shape)],
            ["held-out sequences, per kind", kinds(d), kinds(shape)],
            ["held-out real KITTI frames", _pct(d["cv_real_frames"]["false_removed"]) + " removed, "
             + _pct(d["cv_real_frames"]["true_lost"]) + " lost", _pct(shape["cv_real_frames"]["false_removed"])
             + " removed, " + _pct(shape["cv_real_frames"]["true_lost"]) + " lost"],
            ["ablation: held-out AUC the term brings", ", ".join(f"{t} {a['auc_change']:+.3f}"
                                                                 for t, a in d["ablation"].items()),
             f"mismatch {m['confusion_auc_contribution']:+.3f} on confusions ({m['confusion_auc_held_out_without']:.3f}"
             f" -> {m['confusion_auc_held_out_with']:.3f}); alone {m['auc_alone_confusion_vs_true']:.3f}"]]
    def fitted_on(r: dict[str, Any]) -> str:  # the two columns may come from calibration sets of different sizes
        rows = [v for k, v in r["rows"].items() if k != "real"]
        return f"{sum(v['true'] for v in rows):,} true / {sum(v['false'] for v in rows):,} false simulated rows"

    return table(["", f"shipped rule (`--terms {','.join(d['terms'])}`; {fitted_on(d)})",
                  f"offered the shape (`--terms {','.join(shape['terms'])}`; {fitted_on(shape)})"], rows)


# --------------------------------------------------------------------------- the boosted trees


def render_filter_trees(d: dict[str, Any]) -> list[str]:
    """``pcc calibrate-filter --trees-out``: what the trees add held out (by sequence, per kind; the
    real frames by blocks), and each layout's threshold set on the out-of-fold p_false."""
    s = d["settings"]
    seq, alone = d["by_sequence"]["with_trees"], d["by_sequence"]["sum_alone"]
    kinds = [k for k in seq["per_kind"]]

    def auc_row(f: dict[str, Any]) -> list[str]:
        return [f"{f['auc_false_above_true']:.3f}", pct(f[BUDGET + "_best"]),
                *(f"{f['per_kind'][k]['auc_vs_true']:.3f}" for k in kinds)]

    rows = [[f"the weighted sum alone (held out by sequence, {d['by_sequence']['folds']} folds)", *auc_row(alone)],
            [f"the sum + {s['rounds']} trees of depth {s['depth']} (rate {s['rate']:g}"
             f"{', monotone in the physical terms' if s.get('monotone') else ''}), boosted without the held-out "
             "sequence", *auc_row(seq)]]
    out = table(["held out", "AUC", "removed at <= 2 % lost (best threshold)", *(f"AUC {k}" for k in kinds)], rows)
    real = d.get("real_frames")
    if real is not None:
        out += ["", f"Real frames held out by blocks (trees boosted without the block) at the `{real['layout']}` "
                f"threshold {real['threshold']:.4f}: {pct(real['false_removed'])} of {real['false']} false "
                f"detections removed, {round(real['true_lost'] * real['true'])} / {real['true']} true lost "
                f"(AUC {real['auc_false_above_true']:.3f})."]
    layouts = d["sensor_thresholds"]["layouts"]
    rows = [[k, f"{v['threshold']:.4f}", pct(v['budget'], 2), pct(v['cv_worst_fold'], 2),
             f"{v['rows']['true']:,} / {v['rows']['false']:,}"] for k, v in layouts.items()]
    out += ["", *table(["layout", "threshold", "budget (CV)", "worst held-out fold lost", "true / false rows"], rows)]
    return out


# --------------------------------------------------------------------------- the blocks


FIGURES: dict[str, Figure] = {
    "filter-checked-on": Figure(("filter-nuscenes", *(_synth(s) for s in SENSORS), "filter-trees",
                                 "calibrate-kitti"), render_checked_on),
    "filter-nuscenes": one("filter-nuscenes", render_filter_nuscenes),
    "filter-sensor-from-scans": one("sensor-from-scans", render_sensor_from_scans),
    "filter-nuscenes-kitti-preset": one("filter-nuscenes-kitti-preset", render_nuscenes_kitti_preset),
    "filter-synth": Figure(tuple(_synth(s) for s in SENSORS), render_filter_synth),
    "filter-synth-s123": Figure(tuple(_synth(s, "123") for s in SENSORS),
                                lambda results: render_filter_synth(results, "123")),
    "filter-synth-unseen": Figure(tuple(_synth(s) for s in UNSEEN_SENSORS),
                                  lambda results: render_filter_synth(results, sensors=UNSEEN_SENSORS)),
    "filter-synth-unseen-s123": Figure(tuple(_synth(s, "123") for s in UNSEEN_SENSORS),
                                       lambda results: render_filter_synth(results, "123", sensors=UNSEEN_SENSORS)),
    "filter-calibration": Figure(("filter-calibration", "filter-calibration-shape"), render_filter_calibration),
    "filter-trees": one("filter-trees", render_filter_trees),
    "filter-calibration-kitti": Figure(("calibrate-kitti", "calibrate-kitti-physics"), render_calibration_kitti),
    "filter-term-auc": Figure(("filter-calibration", "calibrate-s99"), render_term_auc),
    "filter-eval-kitti": Figure(("filter-kitti", *(f"filter-kitti-trapcc-{b}" for b in TRAPCC_BACKENDS)),
                                render_eval_kitti),
    "filter-eval-synthcars": Figure(("filter-synthcars-kitti-preset", "filter-synthcars-calibrated"),
                                    render_eval_synthcars),
}
