"""Render the figure tables of the README and docs from committed result files.

A figure is a block of markdown between two marker comments::

    <!-- figure: bench-crop -->
    | boxes | ... |            <- written by this script, never by hand
    Source: docs/results/bench-crop.json (command, commit, date, machine load)
    <!-- /figure -->

Its content comes from one JSON result file, ``docs/results/<source>.json`` (the output of
``pcc bench NAME --json`` or ``pcc eval ... --json``, stored with :func:`store`, which adds the
command, the commit and the date), turned into markdown by the figure's renderer in
:data:`FIGURES`. ``test/test_figures.py`` runs :func:`check`: a table that differs from its
JSON, a marker with no renderer, an unclosed block or a result file without its provenance
fails the test.

Usage (from the repository root)::

    python scripts/render_figures.py                # rewrite every figure block from its JSON
    python scripts/render_figures.py --check        # list the blocks that differ; exit 1 if any
    python scripts/render_figures.py store bench-crop RESULT.json --command "pcc bench crop --repeat 30"
    python scripts/render_figures.py store-bench    # every benchmarks/results/NAME.json as bench-NAME
    make figures                                    # make bench, store-bench, render

Adding a figure: run the command with ``--json``, ``store`` the file under a new name, write a
renderer (a function of the JSON returning the table's lines) into :data:`FIGURES`, put the
two markers where the table goes, and run the script.
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
RESULTS = Path("docs/results")
#: Other processes' CPU use (cores) above which a run is said not to be idle (benchmarks' own rule).
IDLE_CORES = 0.1
BEGIN = re.compile(r"^<!-- figure: ([a-z0-9-]+) -->$")
END = "<!-- /figure -->"


@dataclass(frozen=True)
class Figure:
    """A figure block: the result files it is rendered from (names under ``docs/results/``) and the
    function that turns them (name -> parsed JSON) into the block's markdown lines."""

    sources: tuple[str, ...]
    render: Callable[[dict[str, dict[str, Any]]], list[str]]


def one(source: str, render: Callable[[dict[str, Any]], list[str]]) -> Figure:
    """A figure rendered from a single result file."""
    return Figure((source,), lambda results: render(results[source]))


# --------------------------------------------------------------------------- formatting


def table(header: list[str], rows: list[list[Any]]) -> list[str]:
    """A markdown table."""
    lines = ["| " + " | ".join(header) + " |", "| " + " | ".join("---" for _ in header) + " |"]
    return lines + ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]


def ms(value: float) -> str:
    return f"{value:.2f} ms"


def ratio(value: float) -> str:
    return f"{value:.2f}x"


def met(flag: bool | None) -> str:
    return {True: "met", False: "**not met**", None: "-"}[flag]


def provenance(data: dict[str, Any], source: str) -> str:
    """The line under a figure for each of its sources: which file, command, commit and date, and how
    busy the machine was."""
    p = data["provenance"]
    line = f"Source: `{RESULTS / source}.json` (`{p['command']}`, commit {p['commit']}, {p['date']} UTC"
    machine = p.get("machine") or {}
    cores, others = machine.get("cpu_count"), machine.get("other_processes_cores")
    if others is not None:
        state = "idle" if others <= IDLE_CORES else "not idle, absolute times inflated"
        line += f"; other processes used {others:.2f}{'' if cores is None else f' of {cores}'} cores: {state}"
    return line + ")."


# --------------------------------------------------------------------------- renderers


def _messages_row(d: dict[str, Any]) -> str:
    dense, nan = d["clouds"]["kitti_xyzi"], d["clouds"]["padded32_nan"]
    return (f"NaN cloud: `read_xyz` {ratio(nan['speedup_vs_reference'])} the sensor_msgs_py-equivalent route "
            f"({nan['decode_xyz_ms']:.2f} vs {nan['reference_xyz_ms']:.2f} ms); dense cloud: "
            f"{ratio(dense['speed_vs_copy'])} the speed of a plain numpy copy while checking every point; "
            f"structured view {dense['structured_view_us']:.0f}-{nan['structured_view_us']:.0f} us; encode "
            f"{dense['encode_ms']:.2f} / {nan['encode_ms']:.2f} ms ([docs/messages.md](docs/messages.md))")


def render_bench_messages(d: dict[str, Any]) -> list[str]:
    """docs/messages.md: decode and encode of the two reference clouds."""
    rows = []
    for name, label in (("kitti_xyzi", "kitti_xyzi (123k, dense)"), ("padded32_nan", "padded32_nan (131k, NaN)")):
        c = d["clouds"][name]
        rows.append([f"{label}; {c['kept']:,} kept", f"{c['decode_xyz_ms']:.2f}", f"{c['reference_xyz_ms']:.2f}",
                     ratio(c["speedup_vs_reference"]), f"{c['strided_copy_ms']:.2f}", ratio(c["speed_vs_copy"]),
                     f"{c['structured_view_us']:.1f}", f"{c['encode_ms']:.2f}"])
    header = ["cloud", "read_xyz ms (lower is better)", "reference route ms", "speedup (higher is better)",
              "numpy copy ms", "speed vs copy", "structured view us", "encode ms"]
    return table(header, rows)


def render_bench_crop(d: dict[str, Any]) -> list[str]:
    """docs/instances.md: the crop against open3d's per-box loop and the previous crop
    (``benchmarks/_reference.py``), medians of calls timed interleaved."""
    rows = [[r["boxes"], f"{r['cropped_points']:,}",
             f"{r['ours_min']:.2f} / {r['ours_ms']:.2f} / {r['ours_max']:.2f} ms",
             f"{r['open3d_min']:.2f} / {r['open3d_ms']:.2f} / {r['open3d_max']:.2f} ms",
             ratio(r["speedup_vs_open3d"]), ms(r["93cd59e_ms"]), ratio(r["speedup_vs_93cd59e"]),
             r["points_differing"], r["93cd59e_missed"]] for r in d["rows"]]
    header = ["boxes", "cropped points", "ours min / median / max", "open3d min / median / max",
              "speedup vs open3d (higher is better)", "previous crop, median", "speedup vs previous",
              "points differing from open3d", "points the previous crop missed"]
    return table(header, rows)


# ---- the README's benchmark table: one row per benchmark, each from its own result file


def _row_messages(d: dict[str, Any]) -> list[str]:
    dense, nan, t = d["clouds"]["kitti_xyzi"], d["clouds"]["padded32_nan"], d["targets"]
    figure = (f"NaN cloud: `read_xyz` {ratio(nan['speedup_vs_reference'])} the sensor_msgs_py-equivalent route "
              f"({nan['decode_xyz_ms']:.2f} vs {nan['reference_xyz_ms']:.2f} ms); dense cloud: "
              f"{ratio(dense['speed_vs_copy'])} the speed of a plain numpy copy while checking every point; "
              f"structured view {dense['structured_view_us']:.0f}-{nan['structured_view_us']:.0f} us; encode "
              f"{dense['encode_ms']:.2f} / {nan['encode_ms']:.2f} ms ([docs/messages.md](docs/messages.md))")
    target = (f">= {t['speedup_vs_reference_nan']}x, >= {t['speed_vs_copy_dense']}x copy, "
              f"<= {t['structured_view_us']:.0f} us, <= {t['encode_ms']:.0f} ms")
    return ["`pcc bench messages` (123k-point dense KITTI scan; 131k padded cloud with 10 % NaN)", figure, target,
            met(d["all_targets_met"])]


def _row_synth(d: dict[str, Any]) -> list[str]:
    fps = d["frames_per_s_end_to_end"]
    return ["`pcc bench synth` (full 64-beam SynthCars frames)",
            f"{fps:.1f} frames/s end to end ({d['points_per_frame']:,.0f} points per frame)",
            f">= {d['target_frames_per_s']:.0f} frames/s", met(fps >= d["target_frames_per_s"])]


def _row_convert(d: dict[str, Any]) -> list[str]:
    t = d["targets"]
    return ["`pcc bench convert` (real 123k-point scans to MCAP + zstd-3)",
            f"write {d['write_frames_per_s']:.1f} frames/s, read {d['read_frames_per_s']:.1f} frames/s",
            f">= {t['write_frames_per_s']:.0f}, >= {t['read_frames_per_s']:.0f} frames/s", met(d["targets_met"])]


def _row_crop(d: dict[str, Any]) -> list[str]:
    by = {r["boxes"]: r for r in d["rows"]}
    r30 = by[30]
    others = ", ".join(f"{ratio(by[n]['speedup_vs_open3d'])} at {n}" for n in sorted(by) if n != 30)
    figure = (f"{ratio(r30['speedup_vs_open3d'])} open3d's per-box loop at 30 boxes (medians {r30['ours_ms']:.2f} "
              f"vs {r30['open3d_ms']:.2f} ms; {others}); same point sets as open3d "
              f"([docs/instances.md](docs/instances.md))")
    return ["`pcc bench crop` (real 123k-point KITTI scan)", figure, f">= {d['target_speedup']:.0f}x at 30 boxes",
            met(d["target_met"])]


def _row_complete(d: dict[str, Any]) -> list[str]:
    one = d["threads"]["d1/1"]
    best = d["threads"][f"d1/{d['best_threads']}"]
    others = {b["backend"]: b for b in d["backends"] if "error" not in b}
    figure = (f"PointPnCNet, 1 thread: {ratio(one['speedup'])} the original network path "
              f"({one['fast_inst_s']:.0f} vs {one['original_inst_s']:.0f} instances/s at batch 32), "
              f"{one['of_ceiling']:.0%} of the matrix-product ceiling measured in the same rounds; best setting "
              f"`{d['best_threads']}`: {best['fast_inst_s']:.0f} instances/s")
    routes = d.get("blas_routes") or {}
    at1 = next((r for r in routes.get("rows", []) if r["density"] == 1 and "of_libtorch" in r), None)
    if at1:  # the products' route against the kernels' old libtorch binding
        route = {"Cblas": "MKL's CBLAS", "NumpyDot": "SciPy's BLAS"}.get(routes["route"], routes["route"])
        figure += (f"; products on {route}: {at1['of_libtorch']:.0%} of the 1-thread throughput of the "
                   f"kernels bound to libtorch's `sgemm_` (SciPy's BLAS: {at1['dot_of_libtorch']:.0%}; CPU-time "
                   f"medians of {routes['rounds']} interleaved rounds)")
    if "trapcc" in others:
        figure += f"; TraPCC {others['trapcc']['inst_s']:.0f} instances/s at batch 32"
    if "aml" in others:
        figure += f"; AML {others['aml']['ms_per_instance']:.2f} ms per car incl. marching cubes"
    figure += " ([docs/pointpncnet.md](docs/pointpncnet.md))"
    t = d["targets"]
    target = f">= {t['speedup_b32_min']:.0f}x, >= {t['of_ceiling_min']:.0%} of the ceiling at 1 thread"
    if "of_libtorch_kernels_min" in t:
        target += f"; >= {t['of_libtorch_kernels_min']:.0%} of the old kernels"
        if t["met"] != t["of_libtorch_kernels_met"]:
            return ["`pcc bench complete` (shipped weights, 512-point cars, batch 32)", figure, target,
                    f"{met(t['met'])}; {met(t['of_libtorch_kernels_met'])}"]
    return ["`pcc bench complete` (shipped weights, 512-point cars, batch 32)", figure, target,
            met(t["met"] and t.get("of_libtorch_kernels_met", True))]


def _row_filter(d: dict[str, Any]) -> list[str]:
    rows = d["rows"]
    speedups = [r["speedup"] for r in rows]
    at20 = next(r for r in rows if r["scan"] == "synthcars" and r["boxes"] == 20)
    figure = (f"{min(speedups):.1f}-{max(speedups):.1f}x the previous filter (`benchmarks/_reference.py`), outputs "
              f"{'identical' if all(r['outputs'] == 'identical' for r in rows) else '**differ**'}; 20 cars: "
              f"{at20['ours_ms']:.2f} ms on one thread, {at20['ours2_ms']:.2f} ms with a second")
    if "rule_terms_24858c5_2_ms" in at20:  # the shipped rule's whole measurement, before / after, interleaved
        figure += (f"; the shipped rule's whole measurement (profile terms included) {at20['rule_terms_2_ms']:.2f} "
                   f"ms on two threads against {at20['rule_terms_24858c5_2_ms']:.2f} ms as 24858c5 made it")
    figure += " ([docs/filter.md](docs/filter.md#cost-pcc-bench-filter))"
    return ["`pcc bench filter` (the evidence filter's scan measurements, SynthCars 120k points, 1-100 cars; "
            "real KITTI scan)", figure, "see the pipeline row", "-"]


def _row_pipeline(d: dict[str, Any]) -> list[str]:
    t = d["targets"]
    figure = (f"{ratio(d['speedup_p50'])} the previous pipeline (p50 {d['p50_ms']:.1f} vs "
              f"{d['original_p50_ms']:.1f} ms, each at its best setting), "
              f"{ratio(d['speedup_vs_orig_net_p50'])} the network-only reference; p95 "
              f"{d['p95_ms']:.1f} ms; filter = {d['filter_share_of_complete']:.0%} of completion "
              "([docs/nodes.md](docs/nodes.md#pcc-bench-pipeline))")
    verdict = t["speedup_met"] and t["filter_share_met"] and t["p95_met_here"]
    return [f"`pcc bench pipeline` (SynthCars frame, {d['points']:,} points, {d['cars']} cars, shipped "
            f"{d['backend']}; every output built)", figure,
            f">= {t['speedup_min']}x, p95 <= {t['p95_ms_max_idle']:.0f} ms idle, filter <= "
            f"{t['filter_share_max']:.0%} of completion", met(verdict)]


def _row_hostile(d: dict[str, Any]) -> list[str]:
    bounded, unbounded = d["max_crop_work default"], d["unbounded"]
    figure = (f"default `max_crop_work` against the bound switched off, same process: "
              f"{bounded['s_per_frame']:.3f} vs {unbounded['s_per_frame']:.2f} s per frame, "
              f"{bounded['peak_alloc_mb']:.1f} vs {unbounded['peak_alloc_mb']:.0f} MB peak allocations "
              "([docs/reliability.md](docs/reliability.md))")
    return [f"`pcc bench hostile` ({d['boxes']} boxes of {d['size_m']:.0f} m over a 123k-point KITTI scan)", figure,
            "bounded", met(bounded["s_per_frame"] < unbounded["s_per_frame"]
                           and bounded["peak_alloc_mb"] < unbounded["peak_alloc_mb"])]


BENCH_ROWS: dict[str, Callable[[dict[str, Any]], list[str]]] = {
    "messages": _row_messages, "synth": _row_synth, "convert": _row_convert, "crop": _row_crop,
    "complete": _row_complete, "filter": _row_filter, "pipeline": _row_pipeline, "hostile": _row_hostile,
}


def render_bench_table(results: dict[str, dict[str, Any]]) -> list[str]:
    """README: every benchmark's headline figure, its target and whether this run met it."""
    header = ["benchmark", "figure (ratios: alternatives timed interleaved in one run)", "target", "this run"]
    return table(header, [BENCH_ROWS[name](results[f"bench-{name}"]) for name in BENCH_ROWS])


def render_demo(d: dict[str, Any]) -> list[str]:
    """README: what ``make demo`` prints, its units and which way is better in every header."""
    synth = d["synthcars"]
    completion = table(
        [f"SynthCars completion vs true shapes ({synth['completion'][0]['instances']} cars)",
         "CD-L1 (m, lower is better)", "precision (m, lower is better)", "coverage (m, lower is better)",
         "F-score@1% (0-1, higher is better)"],
        [[r["backend"] + (" (shipped)" if r["backend"] == d["backend"] else ""), f"{r['cd_l1']:.3f}",
          f"{r['precision']:.3f}", f"{r['coverage']:.3f}", f"{r['fscore']:.3f}"] for r in synth["completion"]])

    def row(name: str, half: dict[str, Any] | None) -> list[str]:
        if half is None:
            return [name, "skipped: no KITTI tracking data (docs/datasets.md, Getting real data)", "-", "-", "-"]
        f = half["filter"]
        return [name, f"`{half['filter_config']}`", f"{f['true_kept']} / {f['true_rejected']}",
                f"{f['false_kept']} / {f['false_rejected']}",
                f"{f['precision_before']:.3f} -> {f['precision_after']:.3f}"]

    filtering = table(
        ["detection filter (true = BEV IoU >= 0.3 with a labelled car)", "filter setting",
         "true detections kept / rejected (keep all)", "false detections kept / rejected (reject all)",
         "share of kept detections that are true, before -> after (higher is better)"],
        [row("SynthCars, simulated detector", synth), row("real KITTI 0000, PointRCNN", d["kitti"])])
    return [*completion, "", *filtering]


def _setting(name: str) -> str:
    """``workers 1`` -> ```workers` 1``: the parameter names of a scale row as code."""
    if name == "shipped":
        return name
    return " + ".join(f"`{part.split()[0]}` {' '.join(part.split()[1:])}" for part in name.split(" + "))


def render_bench_scale(d: dict[str, Any]) -> list[str]:
    """docs/nodes.md: the shipped filter node on a 64-beam and a 128-beam frame, and the settings
    that trade speed for something else; then the benchmark's own verdict."""
    rows = [[_setting(r["setting"]), f"{r['points']:,} / {r['cars']} / {r['boxes']}",
             f"{r['p50_ms']:.0f} / {r['p95_ms']:.0f}", f"{r['cpu_p50_ms']:.0f}", f"{r['cpu_bound_hz']:.1f}",
             *(f"{r[stage]:.1f}" for stage in ("decode", "crop", "complete", "filter", "uncanonical", "encode")),
             f"{r['judged']} / {r['passed_on']}", f"{r['peak_rss_mb']:.0f} (+{r['rss_growth_mb']:.0f})"]
            for r in d["rows"]]
    header = ["setting", "points / cars / boxes", "wall p50 / p95 ms (lower is better)", "cpu ms (lower is better)",
              "cpu Hz (higher is better)", "decode", "crop", "complete", "filter", "uncanonical", "encode",
              "judged / passed on", "peak RSS MB (growth)"]
    return [*table(header, rows), "", f"Verdict of this run: {d['verdict']}"]


def _filter_frame(scan: str, rows: list[dict[str, Any]]) -> str:
    points = rows[0]["points"]
    boxes = " / ".join(str(r["boxes"]) for r in rows)
    if scan == "synthcars":
        return f"SynthCars {points // 1000}k points, {boxes} cars"
    return f"KITTI {scan.split()[-1]}, {boxes} boxes"


def _by_scan(d: dict[str, Any]) -> dict[str, list[dict[str, Any]]]:
    scans: dict[str, list[dict[str, Any]]] = {}
    for r in d["rows"]:
        scans.setdefault(r["scan"], []).append(r)
    return scans


def render_filter_terms(d: dict[str, Any]) -> list[str]:
    """docs/filter.md: what each part of the filter's measurement costs (medians), with the
    profile pass and the shipped rule's measurement as 24858c5 made them in parentheses
    (interleaved in the same run) where the result has them."""
    columns: tuple[tuple[str, str | None], ...] = (("beams_ms", None), ("profile_ms", None), ("all_terms_ms", None),
                                                   ("rule_terms_ms", None))
    if "rule_terms_24858c5_2_ms" in d["rows"][0]:
        columns = (("beams_ms", None), ("profile_rule_ms", "profile_24858c5_ms"), ("all_terms_ms", None),
                   ("rule_terms_ms", None), ("rule_terms_2_ms", "rule_terms_24858c5_2_ms"))

    def cell(r: dict[str, Any], c: str, before: str | None) -> str:
        return f"{r[c]:.1f}" + (f" ({r[before]:.1f})" if before else "")

    rows = [[_filter_frame(scan, rs), *(" / ".join(cell(r, c, b) for r in rs) for c, b in columns)]
            for scan, rs in _by_scan(d).items()]
    return table(["frame (ms, lower is better)", *(f"`{c}`" + (" (at 24858c5)" if b else "") for c, b in columns)],
                 rows)


def render_bench_filter(d: dict[str, Any]) -> list[str]:
    """docs/filter.md: the scan measurements against the previous filter, interleaved call by call."""
    rows = [["SynthCars" if r["scan"] == "synthcars" else f"KITTI {r['scan'].split()[-1]}",
             f"{r['points'] // 1000}k", r["boxes"], f"{r['ours_min']:.1f} / {r['ours_ms']:.1f} ms",
             f"{r['ours2_min']:.1f} / {r['ours2_ms']:.1f} ms", f"{r['ref_min']:.1f} / {r['ref_ms']:.1f} ms",
             ratio(r["speedup"]), r["outputs"]] for r in d["rows"]]
    header = ["scan", "points", "boxes", "ours min / median", "ours, workers 2, min / median",
              "previous filter min / median", "speedup, medians (higher is better)", "outputs"]
    return table(header, rows)


# ---- docs/filter.md: the detection filter across sensors and detectors

FILTER_SENSORS = ("hdl64", "vlp16", "vlp32c", "os1_64")


def pct(value: float | None) -> str:
    return "-" if value is None else f"{100 * value:.1f} %"


def render_filter_synth(results: dict[str, dict[str, Any]]) -> list[str]:
    """Per false-positive kind and held-out simulated sensor: removed at the configured threshold
    (the filter and points-in-box at their best threshold for <= 2 % lost), and the true cars lost."""
    kinds = {s: results[f"filter-synth-{s}"]["per_kind"] for s in FILTER_SENSORS}

    def cell(k: dict[str, Any], kind: str) -> str:
        n = k["configured"]["per_group_count"].get(kind)
        if not n:
            return "none"
        best, pib = (k["methods"][m]["per_group_removed"][kind] for m in ("filter", "points-in-box"))
        return f"{pct(k['configured']['per_group_removed'][kind])} ({pct(best)} / {pct(pib)}) of {n}"

    rows = [[kind, *(cell(kinds[s], kind) for s in FILTER_SENSORS)] for kind in ("confusion", "ghost", "far",
                                                                               "misplaced")]
    rows.append(["all false", *(f"{pct(k['configured']['false_removed'])} "
                                f"({pct(k['methods']['filter']['false_removed_at_0.02_lost'])} / "
                                f"{pct(k['methods']['points-in-box']['false_removed_at_0.02_lost'])})"
                                for k in kinds.values())])
    rows.append(["**true cars lost** (by kind label)", *(f"**{k['configured']['true_lost_count']} / {k['true']}** "
                                                          f"({pct(k['configured']['true_lost'])})"
                                                          for k in kinds.values())])
    return table(["kind: configured (filter at the budget / points-in-box)", *FILTER_SENSORS], rows)


def render_filter_nuscenes(d: dict[str, Any]) -> list[str]:
    """The nuScenes check per group: removed at the configured threshold, and by the filter and by
    points-in-box at their best threshold for <= 2 % of the cars lost; then the headline figures."""
    conf, methods = d["configured"], d["methods"]
    rows = [[g, conf["per_group_count"][g], pct(conf["per_group_removed"][g]),
             pct(methods["filter"]["per_group_removed"][g]), pct(methods["points-in-box"]["per_group_removed"][g])]
            for g in sorted(conf["per_group_count"])]
    cars = "; ".join(f"car with {c['returns']} returns at {c['range_m']} m: p_false {c['p_false']:.3f}, {c['status']}"
                     for c in d["well_seen_cars"])
    return [*table(["false group", "boxes", "configured", "filter, best for <= 2 % lost", "points-in-box, same"],
                   rows), "",
            f"Non-vehicle boxes removed at the configured threshold: **{pct(conf['non_vehicle_removed'])}** "
            f"({pct(conf.get('non_vehicle_removed_without_overlap'))} without the `overlap` term); free ground "
            f"{pct(conf['free_ground_removed'])}; cars lost {conf['true_lost_count']} / {d['true']}; {cars}."]


def render_filter_calibration(results: dict[str, dict[str, Any]]) -> list[str]:
    """``pcc calibrate-filter --sim-sensors``: weights, leave-one-sensor-out and leave-one-sequence-out
    figures at each fold's own threshold, the ablation; beside it the same fit offered the shape term."""
    d, shape = results["filter-calibration"], results["filter-calibration-shape"]

    def weights(r: dict[str, Any]) -> str:
        return ", ".join(f"{t} {w:+.2f}" for t, w in r["weights"].items() if w) + f"; bias {r['bias']:+.2f}, " \
            f"threshold {r['threshold']:.3f}"

    def folds(r: dict[str, Any]) -> str:
        return "; ".join(f"{s}: {pct(f['false_removed'])} removed at {pct(f['true_lost'])} lost, confusions "
                         f"{pct(f['per_kind'].get('confusion', {}).get('removed'))}"
                         for s, f in r["cv_by_sensor"]["folds"].items())

    def kinds(r: dict[str, Any]) -> str:
        p = r["cv_by_sequence"]["pooled"]
        return ", ".join(f"{k} {pct(v['removed'])}" for k, v in p["per_kind"].items()) + \
            f" ({pct(p['true_lost'])} true lost; AUC {p['auc_false_above_true']:.3f})"

    m = shape["mismatch"]
    rows = [["weights", weights(d), weights(shape)],
            ["held-out sensor (fold threshold)", folds(d), folds(shape)],
            ["held-out sequences, per kind", kinds(d), kinds(shape)],
            ["held-out real KITTI frames", pct(d["cv_real_frames"]["false_removed"]) + " removed, "
             + pct(d["cv_real_frames"]["true_lost"]) + " lost", pct(shape["cv_real_frames"]["false_removed"])
             + " removed, " + pct(shape["cv_real_frames"]["true_lost"]) + " lost"],
            ["ablation: held-out AUC the term brings", ", ".join(f"{t} {a['auc_change']:+.3f}"
                                                                 for t, a in d["ablation"].items()),
             f"mismatch {m['confusion_auc_contribution']:+.3f} on confusions ({m['confusion_auc_held_out_without']:.3f}"
             f" -> {m['confusion_auc_held_out_with']:.3f}); alone {m['auc_alone_confusion_vs_true']:.3f}"]]
    return table(["", "shipped rule (`--terms " + ",".join(d["terms"]) + "`)", "offered the shape (`+mismatch`)"],
                 rows)


#: Every figure block of the README and docs: marker id -> its result file and renderer.
FIGURES: dict[str, Figure] = {
    "bench-table": Figure(tuple(f"bench-{name}" for name in BENCH_ROWS), render_bench_table),
    "bench-messages": one("bench-messages", render_bench_messages),
    "bench-crop": one("bench-crop", render_bench_crop),
    "demo": one("demo", render_demo),
    "bench-scale": one("bench-scale", render_bench_scale),
    "bench-filter": one("bench-filter", render_bench_filter),
    "bench-filter-terms": one("bench-filter", render_filter_terms),
    "filter-synth": Figure(tuple(f"filter-synth-{s}" for s in FILTER_SENSORS), render_filter_synth),
    "filter-nuscenes": one("filter-nuscenes", render_filter_nuscenes),
    "filter-calibration": Figure(("filter-calibration", "filter-calibration-shape"), render_filter_calibration),
}
#: The benchmarks ``store-bench`` keeps (as ``bench-NAME``): the README table's and those with a figure of their own.
STORED_BENCHMARKS = {source.removeprefix("bench-") for figure in FIGURES.values() for source in figure.sources
                     if source.startswith("bench-")}


# --------------------------------------------------------------------------- the engine


def documents(root: Path) -> list[Path]:
    """The markdown files that may hold figures: the README and docs/."""
    return [root / "README.md", *sorted((root / "docs").rglob("*.md"))]


def load_result(root: Path, source: str) -> dict[str, Any]:
    path = root / RESULTS / f"{source}.json"
    data = json.loads(path.read_text(encoding="utf-8"))
    missing = [k for k in ("command", "commit", "date") if not (data.get("provenance") or {}).get(k)]
    if missing:
        raise ValueError(f"{path}: provenance lacks {missing} (store results with `render_figures.py store`)")
    return data


def rendered(root: Path, figure_id: str) -> list[str]:
    """The lines of a figure block, from its JSON."""
    figure = FIGURES[figure_id]
    results = {source: load_result(root, source) for source in figure.sources}
    lines = [*figure.render(results), ""]
    if len(figure.sources) == 1:
        return [*lines, provenance(results[figure.sources[0]], figure.sources[0])]
    return [*lines, *(f"- {provenance(results[source], source)}" for source in figure.sources)]


def blocks(text: str, where: str) -> list[tuple[str, int, int]]:
    """``(figure id, first content line, end marker line)`` of every block; ValueError naming
    ``where`` and the line for an unclosed block or an unknown id."""
    lines = text.split("\n")
    out, open_at = [], None
    for number, line in enumerate(lines):
        match = BEGIN.match(line.strip())
        if match:
            if open_at is not None:
                raise ValueError(f"{where}:{number + 1}: figure block opened inside another")
            if match.group(1) not in FIGURES:
                raise ValueError(f"{where}:{number + 1}: unknown figure {match.group(1)!r} "
                                 f"(known: {', '.join(sorted(FIGURES))})")
            open_at = (match.group(1), number)
        elif line.strip() == END:
            if open_at is None:
                raise ValueError(f"{where}:{number + 1}: {END} without an opening marker")
            out.append((open_at[0], open_at[1] + 1, number))
            open_at = None
    if open_at is not None:
        raise ValueError(f"{where}:{open_at[1] + 1}: figure {open_at[0]!r} is never closed ({END})")
    return out


def render_text(root: Path, text: str, where: str) -> tuple[str, list[str]]:
    """``text`` with every figure block rendered afresh, and the ids of the blocks that changed."""
    lines = text.split("\n")
    changed = []
    for figure_id, start, end in reversed(blocks(text, where)):
        new = rendered(root, figure_id)
        if lines[start:end] != new:
            changed.append(figure_id)
            lines[start:end] = new
    return "\n".join(lines), changed[::-1]


def check(root: Path = ROOT) -> list[str]:
    """Every problem with the figures of ``root``'s README and docs (empty: all match their JSON)."""
    problems, used = [], set()
    for path in documents(root):
        where = str(path.relative_to(root))
        try:
            text = path.read_text(encoding="utf-8")
            used.update(figure_id for figure_id, _, _ in blocks(text, where))
            _, changed = render_text(root, text, where)
        except (OSError, ValueError, KeyError) as exc:
            problems.append(f"{where}: {exc}")
            continue
        problems += [f"{where}: figure {figure_id!r} differs from its JSON" for figure_id in changed]
    problems += [f"figure {figure_id!r} appears in no document" for figure_id in sorted(set(FIGURES) - used)]
    return problems


def render_all(root: Path = ROOT) -> list[str]:
    """Rewrite every figure block; ``where: id`` of each block that changed."""
    out = []
    for path in documents(root):
        where = str(path.relative_to(root))
        text = path.read_text(encoding="utf-8")
        new, changed = render_text(root, text, where)
        if changed:
            path.write_text(new, encoding="utf-8")
            out += [f"{where}: {figure_id}" for figure_id in changed]
    return out


def git_commit(root: Path) -> str:
    """The checkout's short commit, ``-dirty`` when the package or benchmarks have uncommitted changes."""
    def git(*args: str) -> str:
        return subprocess.run(["git", *args], cwd=root, capture_output=True, text=True, check=True).stdout.strip()

    commit = git("rev-parse", "--short", "HEAD")
    return commit + ("-dirty" if git("status", "--porcelain", "--", "pcc_ros", "benchmarks") else "")


def store(root: Path, name: str, result: Path, command: str | None = None) -> Path:
    """Copy a result JSON to ``docs/results/NAME.json`` with its provenance: the command (``command``,
    else the one a benchmark recorded), and the commit and date the benchmark recorded (``run``), else
    the checkout's commit and now."""
    data = json.loads(result.read_text(encoding="utf-8"))
    run = data.get("run") or {}
    command = command or run.get("command")
    if not command:
        raise SystemExit(f"{result}: no command recorded; pass --command as a reader would rerun it")
    data["provenance"] = {
        "command": command,
        "commit": run.get("commit") or git_commit(root),
        "date": (run.get("utc") or time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime()))[:16],
        "machine": {"cpu_count": data.get("cpu_count"), "other_processes_cores": run.get("other_processes_cores")},
    }
    out = root / RESULTS / f"{name}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(data, indent=1, sort_keys=True) + "\n", encoding="utf-8")
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--check", action="store_true", help="list the blocks that differ from their JSON; exit 1")
    sub = parser.add_subparsers(dest="action")
    keep = sub.add_parser("store", help="store a result JSON under docs/results/ with its provenance")
    keep.add_argument("name", help="the result's name (docs/results/NAME.json)")
    keep.add_argument("result", type=Path, help="the JSON a `pcc bench NAME --json` or `pcc eval --json` wrote")
    keep.add_argument("--command", help="the command that produced it, as a reader would rerun it "
                      "(default: the one a benchmark's JSON records)")
    benches = sub.add_parser("store-bench", help="store every benchmark result of a folder as bench-NAME")
    benches.add_argument("folder", type=Path, nargs="?", default=Path("benchmarks/results"),
                         help="where `make bench` wrote them (default benchmarks/results)")
    args = parser.parse_args(argv)
    if args.action == "store":
        print(store(ROOT, args.name, args.result, args.command))
        return 0
    if args.action == "store-bench":
        for result in sorted(args.folder.glob("*.json")):
            if result.stem in STORED_BENCHMARKS:
                print(store(ROOT, f"bench-{result.stem}", result))
        return 0
    if args.check:
        problems = check(ROOT)
        print("\n".join(problems) or "every figure matches its JSON")
        return 1 if problems else 0
    print("\n".join(render_all(ROOT)) or "every figure was already up to date")
    return 0


if __name__ == "__main__":
    sys.exit(main())
