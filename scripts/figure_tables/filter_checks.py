"""docs/filter.md's checks of the detection filter: ``pcc eval detections --json`` on the real and
simulated frames (nuScenes, KITTI + PointRCNN, SynthCars per sensor) and ``pcc calibrate-filter
--json`` (the shipped default across sensors, the KITTI preset), stored under ``docs/results/``."""

from __future__ import annotations

from typing import Any

from .base import Figure, pct, table

#: The simulated sensors of the per-kind check, in the docs' column order.
SENSORS = ("hdl64", "vlp16", "vlp32c", "os1_64")
#: The false-positive kinds of SynthCars' simulated detector, and the real frames' false detections.
KINDS = ("confusion", "ghost", "far", "misplaced")
#: The profile terms' AUC table: the terms in the docs' order, ``free_space`` last for scale.
AUC_TERMS = ("depth", "above", "overlap", "spill", "fill", "top", "free_space")
#: The trapcc rule's completion backends, as the eval-on-KITTI table lists them.
TRAPCC_BACKENDS = ("pointpncnet", "trapcc", "aml")
BUDGET = "false_removed_at_0.02_lost"


def _synth(sensor: str) -> str:
    return f"filter-synthcars-{sensor}"


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


def render_nuscenes_groups(results: dict[str, dict[str, Any]]) -> list[str]:
    """Per group of false boxes: removed at the configured threshold, by the filter and by the
    points-in-box count at their best threshold for the loss budget; with the check's NMS rule and
    without it (``--nms-iou 1``)."""
    nms, every = results["filter-nuscenes"], results["filter-nuscenes-every-box"]
    groups = sorted(set(nms["configured"]["per_group_count"]) | set(every["configured"]["per_group_count"]))

    def cells(d: dict[str, Any], group: str) -> list[str]:
        count = d["configured"]["per_group_count"].get(group)
        if not count:
            return ["0", "-", "-", "-"]
        return [str(count), pct(d["configured"]["per_group_removed"][group]),
                pct(d["methods"]["filter"]["per_group_removed"][group]),
                pct(d["methods"]["points-in-box"]["per_group_removed"][group])]

    rows = [[group, *cells(nms, group), *cells(every, group)] for group in groups]
    rows.append(["all false", str(nms["false"] - sum(nms["suppressed_by_nms"].values())),
                 pct(nms["configured"]["false_removed"]), pct(nms["methods"]["filter"][BUDGET]),
                 pct(nms["methods"]["points-in-box"][BUDGET]), str(every["false"]),
                 pct(every["configured"]["false_removed"]), pct(every["methods"]["filter"][BUDGET]),
                 pct(every["methods"]["points-in-box"][BUDGET])])
    rule = f"NMS rule (BEV IoU {nms['nms_iou']})"
    header = ["false group (removed: higher is better)", f"{rule}: boxes", "configured", "filter at <= 2 % lost",
              "points-in-box at <= 2 % lost", "every box (`--nms-iou 1`): boxes", "configured",
              "filter at <= 2 % lost", "points-in-box at <= 2 % lost"]
    dropped = ", ".join(f"{group} {n}" for group, n in sorted(nms["suppressed_by_nms"].items()))
    kitti = results["filter-nuscenes-kitti-preset"]
    preset = "; ".join(f"score {s}: {round(v['true_lost'] * kitti['true'])} / {kitti['true']}"
                       for s, v in kitti["by_score"].items())
    lines = [
        f"{nms['frames']} frame, {nms['true']} annotated cars, {nms['false']} false boxes "
        f"({nms['ground_boxes']} free-ground boxes asked for); the NMS rule dropped {dropped}.",
        "",
        *table(header, rows),
        "",
        f"With the NMS rule: {_nuscenes_summary(nms)}. Every box: non-vehicles "
        f"{pct(every['configured']['non_vehicle_removed'])} configured, "
        f"{pct(every['configured']['non_vehicle_removed_without_overlap'])} without `overlap` "
        f"({every['configured']['non_vehicle_overlapping_another']} overlap another box; "
        f"{nms['configured']['non_vehicle_overlapping_another']} with the rule).",
        "",
        f"Cars rejected with the KITTI preset (`{kitti['provenance']['command'].split('--config ')[1].split()[0]}`): "
        f"{preset}.",
    ]
    return lines


# --------------------------------------------------------------------------- SynthCars per kind


def render_synthcars_kinds(results: dict[str, dict[str, Any]]) -> list[str]:
    """Per false-positive kind and simulated sensor: removed at the configured threshold, and (in
    parentheses) by the filter and by points-in-box at the loss budget."""
    def cell(d: dict[str, Any], kind: str) -> str:
        k = d["per_kind"]
        count = k["configured"]["per_group_count"].get(kind)
        if not count:
            return "none"
        return (f"{pct(k['configured']['per_group_removed'][kind])} "
                f"({pct(k['methods']['filter']['per_group_removed'][kind])} / "
                f"{pct(k['methods']['points-in-box']['per_group_removed'][kind])}) of {count}")

    def every(d: dict[str, Any]) -> str:
        k = d["per_kind"]
        return (f"{pct(k['configured']['false_removed'])} ({pct(k['methods']['filter'][BUDGET])} / "
                f"{pct(k['methods']['points-in-box'][BUDGET])})")

    def lost(d: dict[str, Any]) -> str:
        k = d["per_kind"]
        return f"{k['configured']['true_lost_count']} / {k['true']}"

    rows = [[kind, *(cell(results[_synth(s)], kind) for s in SENSORS)] for kind in KINDS]
    rows.append(["all false", *(every(results[_synth(s)]) for s in SENSORS)])
    rows.append(["true cars lost (lower is better)", *(lost(results[_synth(s)]) for s in SENSORS)])
    header = ["kind: removed at the configured threshold (filter at <= 2 % lost / points-in-box); higher is better",
              *SENSORS]
    return table(header, rows)


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
    nus, default, kitti = results["filter-nuscenes"], results["calibrate-default"], results["calibrate-kitti"]

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
         "PointRCNN", f"held out by blocks of 4 frames: {_held_out(default['cv_real_frames'])}"],
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
         f"{pct(d['max_lost'])} of the calibration set's true detections)", f"{d['threshold']:.3f}"],
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


def render_calibration_default(results: dict[str, dict[str, Any]]) -> list[str]:
    """The shipped default's calibration across simulated sensors: rows, weights, held out by sensor and
    by sequence (with the ray terms alone beside), and the ablation."""
    d, ray = results["calibrate-default"], results["calibrate-default-ray-terms"]
    folds, ray_folds = d["cv_by_sensor"]["folds"], ray["cv_by_sensor"]["folds"]
    by_sequence, ray_sequence = d["cv_by_sequence"]["pooled"], ray["cv_by_sequence"]["pooled"]

    def kinds(pooled: dict[str, Any]) -> str:
        return ", ".join(f"{k} {pct(v['removed'], 0)}" for k, v in pooled["per_kind"].items())

    def sequences(pooled: dict[str, Any]) -> str:
        return (f"{kinds(pooled)} ({pct(pooled['true_lost'])} true lost; pooled {pct(pooled['false_removed'])} "
                f"removed, {pct(pooled[BUDGET + '_best'])} at the best <= 2 % threshold, AUC "
                f"{pooled['auc_false_above_true']:.3f})")

    ablation = sorted(d["ablation"].items(), key=lambda item: -item[1]["auc_change"])
    rows = [
        ["rows", ", ".join(f"{k} {v['true']} true / {v['false']} false" for k, v in d["rows"].items())],
        ["weights", f"{_weights(d)}; threshold {d['threshold']:.3f}"],
        ["held-out sensor: removed at the fold's threshold, true lost, AUC (ray terms only)",
         "; ".join(f"{s}: {_cv(f)} ({_cv(ray_folds[s])})" for s, f in folds.items())],
        ["held-out sequences, removed per kind",
         f"{sequences(by_sequence)}. Ray terms only: {sequences(ray_sequence)}"],
        ["ablation: held-out AUC (removed at <= 2 % lost) the term brings",
         ", ".join(f"{term} {a['auc_change']:+.3f} ({100 * a['removed_at_0.02_change']:+.1f} points)"
                   for term, a in ablation)],
    ]
    return table(["shipped default", "value"], rows)


def render_term_auc(results: dict[str, dict[str, Any]]) -> list[str]:
    """Each measured term alone: AUC of a kind's boxes scoring above the true cars, on the calibration
    rows / on held-out rows of seed 99 (the real frames only in the first)."""
    d, s99 = results["calibrate-default"], results["calibrate-s99"]
    real = "real false" in next(iter(d["term_auc"].values()))

    def row(term: str) -> list[str]:
        label = f"(`{term}`, for scale)" if term == "free_space" else f"`{term}`"
        cells = [f"{d['term_auc'][term][k]:.3f} / {s99['term_auc'][term][k]:.3f}" for k in KINDS]
        return [label, *cells, *([f"{d['term_auc'][term]['real false']:.3f}"] if real else [])]

    header = ["term (AUC: 0.5 chance, 1 every false box above every true car)", *KINDS,
              *(["KITTI false"] if real else [])]
    return table(header, [row(term) for term in AUC_TERMS])


def render_spill_fill(results: dict[str, dict[str, Any]]) -> list[str]:
    """The shipped rule refitted with ``spill`` and ``fill`` against the rule itself, held out by sequence."""
    d, shipped = results["calibrate-default-spill-fill"], results["calibrate-default"]
    new, old = d["cv_by_sequence"]["pooled"], shipped["cv_by_sequence"]["pooled"]
    return [f"Refitted with them (`--terms {','.join(d['terms'])}`), their weights come out "
            f"{d['weights']['spill']:+.3f} (`spill`) and {d['weights']['fill']:+.3f} (`fill`); held out by sequence, "
            f"confusions removed {pct(new['per_kind']['confusion']['removed'])} against "
            f"{pct(old['per_kind']['confusion']['removed'])} without them "
            f"(of {old['per_kind']['confusion']['count']}), "
            f"AUC {new['auc_false_above_true']:.3f} against {old['auc_false_above_true']:.3f}."]


def render_shape_term(results: dict[str, dict[str, Any]]) -> list[str]:
    """The rule fitted with the shape mismatch (TraPCC's car-constrained completion) against the same
    terms without it."""
    d = results["calibrate-shape"]
    m, ablation = d["mismatch"], d["ablation"]["mismatch"]
    removed_with = d["cv_by_sequence"]["pooled"][BUDGET + "_best"]
    folds = d["cv_by_sensor"]["folds"]
    per_sensor = " / ".join(pct(f["per_kind"].get("confusion", {}).get("removed", 0), 0) for f in folds.values())
    return [f"`w_mismatch` **{m['weight']:+.3f}** ({_weights(d)}; threshold {d['threshold']:.3f}, `mismatch_mean` "
            f"{d['mismatch_mean']:.3f}, the training mean); alone the mismatch ranks confusions above true cars at "
            f"AUC {m['auc_alone_confusion_vs_true']:.3f}; held out, the rule's AUC on confusions is "
            f"{m['confusion_auc_held_out_with']:.3f} with it and {m['confusion_auc_held_out_without']:.3f} without "
            f"(**{m['confusion_auc_contribution']:+.3f}**), over all false boxes {ablation['auc_change']:+.3f}; its "
            f"removal at <= 2 % lost {100 * ablation['removed_at_0.02_change']:+.1f} points ({pct(removed_with)} "
            f"with it, {pct(ablation['removed_at_0.02_without'])} without); per held-out sensor confusions removed "
            f"{per_sensor} ({' / '.join(folds)})."]


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


# --------------------------------------------------------------------------- the blocks


FIGURES: dict[str, Figure] = {
    "filter-checked-on": Figure(("filter-nuscenes", *(_synth(s) for s in SENSORS), "calibrate-default",
                                         "calibrate-kitti"), render_checked_on),
    "filter-nuscenes": Figure(("filter-nuscenes", "filter-nuscenes-every-box", "filter-nuscenes-kitti-preset"),
                              render_nuscenes_groups),
    "filter-synthcars-kinds": Figure(tuple(_synth(s) for s in SENSORS), render_synthcars_kinds),
    "filter-calibration-kitti": Figure(("calibrate-kitti", "calibrate-kitti-physics"), render_calibration_kitti),
    "filter-calibration-default": Figure(("calibrate-default", "calibrate-default-ray-terms"),
                                         render_calibration_default),
    "filter-term-auc": Figure(("calibrate-default", "calibrate-s99"), render_term_auc),
    "filter-spill-fill": Figure(("calibrate-default-spill-fill", "calibrate-default"), render_spill_fill),
    "filter-shape-term": Figure(("calibrate-shape",), render_shape_term),
    "filter-eval-kitti": Figure(("filter-kitti", *(f"filter-kitti-trapcc-{b}" for b in TRAPCC_BACKENDS)),
                                render_eval_kitti),
    "filter-eval-synthcars": Figure(("filter-synthcars-kitti-preset", "filter-synthcars-calibrated"),
                                    render_eval_synthcars),
}
