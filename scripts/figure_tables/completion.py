"""The completion backends' speed figures (``pcc bench complete --json``): docs/pointpncnet.md's thread
and density sweep, docs/trapcc.md's and docs/aml.md's per-backend rows."""

from __future__ import annotations

from typing import Any

from .base import Figure, one, ratio, table

_THREADS = {"1": "1", "2": "2 (intra-op)", "2x1": "2x1 (2 workers x 1)"}


def _batch(d: dict[str, Any]) -> int:
    """The batch of the thread sweep: instances per second times seconds per call."""
    t = next(iter(d["threads"].values()))
    return round(t["fast_inst_s"] * t["fast_ms"] / 1000)


def render_complete_threads(d: dict[str, Any]) -> list[str]:
    """PointPnCNet's paths per decode density and thread setting, timed round-robin in one process."""
    rows = []
    for t in d["threads"].values():
        points = d["densities"][str(t["density"])]["output_points"]
        rows.append([f"{t['density']} ({points})", _THREADS.get(t["threads"], t["threads"]),
                     f"{t['original_ms']:.1f} ms",
                     f"{t['fast_ops_ms']:.1f} ms", f"{t['fast_layers_ms']:.1f} ms",
                     f"{t['fast_min_ms']:.1f} / {t['fast_ms']:.1f} / {t['fast_max_ms']:.1f} ms",
                     f"{t['original_inst_s']:.0f} -> {t['fast_inst_s']:.0f}", ratio(t["speedup"]),
                     f"{t['gflop_s']:.1f}", f"{t['mm_gflop_s']:.1f}",
                     f"{t['of_ceiling']:.0%} / {t['of_ceiling_min']:.0%}"])
    header = ["density (points)", "threads", "original path (lower is better)", "fast_ops", "fast_layers",
              "fast (min / median / max)", "inst/s orig -> fast (higher is better)", "speedup",
              "GFLOP/s executed", "ceiling GFLOP/s", "of ceiling (median / least-disturbed)"]
    flops = ", ".join(f"{v['executed_flops_per_instance'] / 1e6:.1f} MFLOP per instance executed at density {k} "
                      f"({v['nominal_flops_per_instance'] / 1e6:.1f} as defined)" for k, v in d["densities"].items())
    diff = max(v["output_max_abs_diff"] for v in d["densities"].values())
    return [*table(header, rows), "",
            f"Batch {_batch(d)}, {d['inputs']}; {flops}; the "
            f"paths' outputs agree within {diff:.1e} canonical units."]


def render_complete_backends(d: dict[str, Any]) -> list[str]:
    """Every backend's throughput at batch 32 and one instance's latency, at PointPnCNet's best setting."""
    rows = [[b["backend"], f"{b['ms_per_instance']:.2f}", f"{b['inst_s']:.0f}", f"{b['latency_ms_b1']:.3g} ms",
             "yes" if b.get("scene_context") else "no", b["weights"]] for b in d["backends"] if "error" not in b]
    best = d["threads"][f"d1/{d['best_threads']}"]
    rows.append([f"PointPnCNet (fast path, density 1, `{d['best_threads']}`)", f"{best['fast_ms'] / _batch(d):.2f}",
                 f"{best['fast_inst_s']:.0f}", "", "no", "shipped"])
    header = ["backend", f"ms per instance at batch {_batch(d)} (lower is better)", "instances/s (higher is better)",
              "one instance (batch 1)", "scene context", "weights"]
    return table(header, rows)


FIGURES: dict[str, Figure] = {
    "bench-complete-threads": one("bench-complete", render_complete_threads),
    "bench-complete-backends": one("bench-complete", render_complete_backends),
}
