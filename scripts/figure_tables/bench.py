"""The benchmarks' figures (``pcc bench NAME --json``, stored as ``docs/results/bench-NAME.json``) and
``make demo``'s tables: the README's benchmark table and the per-benchmark tables of the docs."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from .base import Figure, met, ms, one, ratio, table


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


def _row_startup(d: dict[str, Any]) -> list[str]:
    starts = d["starts"]
    node = {n: starts.get(f"built/{n}/cold") for n in ("completion_node", "detection_filter_node")}
    warm = starts.get("built/completion_node/warm")
    unbuilt = starts.get("unbuilt/completion_node/cold")
    parts = [f"`{n}` {s['subscriptions_live_s']:.1f} s, {s['answered']}/{s['frames']} real KITTI frames answered"
             f"{' from the first' if s['first_frame_answered'] else ''}" for n, s in node.items() if s]
    figure = "cold start on a fresh read-only install: " + "; ".join(parts)
    if warm:
        figure += f"; warm {warm['subscriptions_live_s']:.1f} s"
    if unbuilt:
        figure += f"; without the kernels compiled at build time {unbuilt['subscriptions_live_s']:.1f} s"
    figure += " ([docs/nodes.md](docs/nodes.md))"
    ok = all(s and s["subscriptions_live_s"] <= 5.0 and s["first_frame_answered"] and s["answered"] == s["frames"]
             for s in node.values())
    return ["`pcc bench startup` (process start to live subscriptions, shipped YAML)", figure,
            "<= 5 s, every frame answered from the first", met(ok)]


BENCH_ROWS: dict[str, Callable[[dict[str, Any]], list[str]]] = {
    "messages": _row_messages, "synth": _row_synth, "convert": _row_convert, "crop": _row_crop,
    "complete": _row_complete, "filter": _row_filter, "pipeline": _row_pipeline, "hostile": _row_hostile,
    "startup": _row_startup,
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




# ---- docs/nodes.md's `pcc bench pipeline` and docs/filter.md's cost sentences

_THREADS = {"1": "1", "2": "2 (intra-op)", "2x1": "2x1 (`workers` 2)"}


def render_pipeline_threads(d: dict[str, Any]) -> list[str]:
    """Each thread setting: the three alternatives' p50 / p95, interleaved frame by frame; then the
    headline, best against best."""
    rows = []
    for name, t in d["threads"].items():
        fast = t["fast"]
        best = "**" if name == d["best_threads"] else ""
        rows.append([_THREADS.get(name, name), f"{t['original_p50']:.1f} / {t['original_p95']:.1f} ms",
                     f"{t['orig_net_p50']:.1f} ms",
                     f"{fast['min_ms']:.1f} / {best}{fast['median_ms']:.1f}{best} / {fast['p95_ms']:.1f} / "
                     f"{fast['max_ms']:.1f} ms", ratio(t["speedup_p50"]), ratio(t["speedup_vs_orig_net"])])
    header = ["threads", "original p50 / p95 (lower is better)", "orig_net p50", "fast min / p50 / p95 / max",
              "fast vs original (higher is better)", "fast vs orig_net"]
    headline = (f"Headline (each alternative at its own best setting; fast at `{d['best_threads']}`, the original "
                f"at `{d['original_threads']}`): **{ratio(d['speedup_p50'])}** today's pipeline "
                f"({d['original_p50_ms']:.1f} -> {d['p50_ms']:.1f} ms), **{ratio(d['speedup_vs_orig_net_p50'])}** "
                f"the network-only reference ({d['orig_net_p50_ms']:.1f} ms); completed clouds equal within "
                f"{d['output_max_abs_diff_m']:.1e} m; {d['cars']} cars, {d['points']:,} points, {d['backend']}.")
    return [*table(header, rows), "", headline]


def render_pipeline_stages(d: dict[str, Any]) -> list[str]:
    """The stages' medians of the three alternatives at their best settings."""
    stages = [r["stage"].removesuffix("_ms") for r in d["stages_ms"]]
    cells = [" / ".join(f"{r[k]:.1f}" for k in ("original_p50", "orig_net_p50", "fast_p50")) for r in d["stages_ms"]]
    return table([f"{s} (ms: original / orig_net / fast)" if i == 0 else s for i, s in enumerate(stages)], [cells])


def render_pipeline_scaling(d: dict[str, Any]) -> list[str]:
    """The fast path over cars and points (medians, ms)."""
    stages = ("decode", "crop", "complete", "filter", "uncanonical", "encode")
    rows = [[r["cars"], f"{r['points'] // 1000}k", f"{r['p50_ms']:.1f}", f"{r['p95_ms']:.1f}",
             *(f"{r[s]:.1f}" for s in stages)] for r in d["scaling"]]
    return table(["cars", "points", "p50 ms (lower is better)", "p95", *stages], rows)


def render_pipeline_share(d: dict[str, Any]) -> list[str]:
    """docs/filter.md: the filter stage's share of the completion stage, the target and the verdict."""
    stages = {r["stage"]: r["fast_p50"] for r in d["stages_ms"]}
    t = d["targets"]
    verdict = "met" if t["filter_share_met"] else "not met"
    return [f"The filter stage takes {stages['filter_ms']:.1f} ms against the completion's "
            f"{stages['complete_ms']:.1f} ms at the best setting of the run (`{d['best_threads']}`; {d['cars']} cars, "
            f"{d['points']:,} points, shipped {d['backend']}): **{d['filter_share_of_complete']:.0%} of the "
            f"completion; the target of at most {t['filter_share_max']:.0%} is {verdict}**."]


def render_filter_profile_gain(d: dict[str, Any]) -> list[str]:
    """docs/filter.md: the profile pass and the rule's whole measurement against 24858c5, interleaved."""
    rows = {(r["scan"], r["boxes"]): r for r in d["rows"]}
    r20 = rows[("synthcars", 20)]
    others = [r["profile_24858c5_ms"] / r["profile_rule_ms"] for key, r in rows.items() if key != ("synthcars", 20)]
    return [f"The profile pass the shipped rule needs, against the same work as 24858c5 did it: 20 cars "
            f"{r20['profile_rule_ms']:.1f} against {r20['profile_24858c5_ms']:.1f} ms "
            f"({ratio(r20['profile_24858c5_ms'] / r20['profile_rule_ms'])}; {ratio(min(others))}-"
            f"{ratio(max(others))} on the other frames), with the same values bit for bit; the shipped rule's "
            f"whole measurement on two threads {r20['rule_terms_2_ms']:.1f} against "
            f"{r20['rule_terms_24858c5_2_ms']:.1f} ms."]


# ---- docs/datasets.md's and docs/reliability.md's benchmark tables


def render_bench_convert(d: dict[str, Any]) -> list[str]:
    """Bag write / read throughput and size per storage and compression."""
    raw = d["configs"]["mcap none"]["mb_per_frame"]
    rows = [[f"**{name}**" if "default" in name else name, f"{c['write_frames_per_s']:.0f}",
             f"{c['read_frames_per_s']:.0f}", f"{c['mb_per_frame']:.2f}", f"{c['mb_per_frame'] / raw:.2f}"]
            for name, c in d["configs"].items()]
    t = d["targets"]
    header = ["config", "write frames/s (higher is better)", "read frames/s (higher is better)",
              "MB/frame (lower is better)", "size vs. raw MCAP"]
    verdict = (f"Targets: >= {t['write_frames_per_s']:.0f} frames/s written and >= {t['read_frames_per_s']:.0f} "
               f"frames/s read with the default: {'met' if d['targets_met'] else '**not met**'} "
               f"({d['write_frames_per_s']:.0f} / {d['read_frames_per_s']:.0f}); {d['source']}, "
               f"{d['points_per_frame']:,.0f} points per frame.")
    return [*table(header, rows), "", verdict]


def render_bench_hostile(d: dict[str, Any]) -> list[str]:
    """The work bound against none: time, memory and what the frame's boxes became."""
    rows = []
    for key, label in (("max_crop_work default", "`max_crop_work` default"), ("unbounded", "bound switched off")):
        r = d[key]
        skipped = ", ".join(f"{why} {n}" for why, n in r["skipped"].items()) or "-"
        rows.append([label, f"{r['s_per_frame']:.3f}", f"{r['peak_alloc_mb']:.1f} MB", r["boxes_judged"],
                     r["boxes_completed"], r["boxes_unjudged"], skipped])
    header = [f"pipeline ({d['boxes']} boxes of {d['size_m']:.0f} m, {d['points']:,} points)",
              "s per frame (lower is better)", "peak allocations (lower is better)", "judged", "completed",
              "unjudged", "skipped (why: count)"]
    return table(header, rows)


# ---- docs/nodes.md's GPU table: `pcc bench gpu` (run on a machine with CUDA; stored as measured there)


def render_bench_gpu(d: dict[str, Any]) -> list[str]:
    """Each learned backend's batch on CUDA (float32, ``half_precision``) against the same machine's CPU
    completer: median ms per batch, the speed-up, and how far the outputs stray from the CPU's."""
    by = {(r["backend"], r["batch"], r["setting"]): r for r in d["rows"]}
    rows = []
    for backend, batch in dict.fromkeys((r["backend"], r["batch"]) for r in d["rows"]):
        cpu, fp32, fp16 = (by[(backend, batch, s)] for s in ("cpu", "cuda_fp32", "cuda_fp16"))
        rows.append([backend, batch, f"{cpu['median_ms']:.1f}", f"{fp32['median_ms']:.1f}", f"{fp16['median_ms']:.1f}",
                     ratio(cpu["median_ms"] / fp32["median_ms"]), ratio(cpu["median_ms"] / fp16["median_ms"]),
                     f"{fp32['cd_l1_vs_cpu']:.1e} / {fp16['cd_l1_vs_cpu']:.1e}",
                     "yes" if fp32["agrees"] and fp16["agrees"] else "**no**"])
    header = ["backend", "batch", "CPU ms (median)", "CUDA float32 ms", "CUDA float16 ms",
              "speed-up float32 (higher is better)", "speed-up float16", "largest CD-L1 vs CPU (float32 / float16)",
              "within tolerance"]
    run = d["run"]
    where = (f"Measured on an {d['device']} (torch {d['torch']}) on {run['utc'][:10]}, against that machine's CPU "
             f"completer on one thread; {d['inputs']}, medians of the interleaved rounds of `{run['command']}`.")
    return [where, "", *table(header, rows)]


FIGURES: dict[str, Figure] = {
    "bench-table": Figure(tuple(f"bench-{name}" for name in BENCH_ROWS), render_bench_table),
    "bench-messages": one("bench-messages", render_bench_messages),
    "bench-crop": one("bench-crop", render_bench_crop),
    "demo": one("demo", render_demo),
    "bench-scale": one("bench-scale", render_bench_scale),
    "bench-filter": one("bench-filter", render_bench_filter),
    "bench-filter-terms": one("bench-filter", render_filter_terms),
    "bench-filter-profile-gain": one("bench-filter", render_filter_profile_gain),
    "bench-pipeline-share": one("bench-pipeline", render_pipeline_share),
    "bench-pipeline-threads": one("bench-pipeline", render_pipeline_threads),
    "bench-pipeline-stages": one("bench-pipeline", render_pipeline_stages),
    "bench-pipeline-scaling": one("bench-pipeline", render_pipeline_scaling),
    "bench-convert": one("bench-convert", render_bench_convert),
    "bench-hostile": one("bench-hostile", render_bench_hostile),
    "bench-gpu": one("bench-gpu", render_bench_gpu),
}
