"""docs/nodes.md's start-up figures: ``pcc bench startup --unbuilt`` (an installed node's way to its
first frame, with and without the build's compiled kernels) and ``pcc bench nodes`` (each node's
stages and memory, all stages against its own)."""

from __future__ import annotations

from typing import Any

from .base import Figure, one, table


def render_startup(d: dict[str, Any]) -> list[str]:
    """One row per install / node / start: wall seconds to the node's subscriptions on the graph, the
    CPU seconds that cost, the frames answered and the first answer's latency."""
    rows = [[f"kernels {s['install']}" if s["install"] == "built" else "`PCC_BUILD_KERNELS=0`", node, start,
             f"{s['subscriptions_live_s']:.2f} s", f"{s['cpu_s_to_live']:.2f}", f"{s['answered']}/{s['frames']}",
             f"{s['first_answer_latency_ms']:.0f} ms" if s["first_frame_answered"] else "not answered"]
            for key, s in d["starts"].items() for _, node, start in [key.split("/")]]
    header = ["install", "node", "start", "live (wall, lower is better)", "CPU s to live (lower is better)",
              "frames answered", "first answer"]
    installs = {s["install"]: s["install_s"] for s in d["starts"].values()}
    note = "Install times (colcon `setup.py install`, the build's kernel compilation included): " + ", ".join(
        f"{name} {seconds:.1f} s" for name, seconds in installs.items()) + "."
    return [*table(header, rows), "", note]


def render_nodes(d: dict[str, Any]) -> list[str]:
    """Each node with every stage (as before the split) against its own stages only."""
    def ms(v: dict[str, Any], stage: str) -> str:
        value = v["stage_median_ms"].get(stage)
        return "-" if value is None else f"{value:.1f} ms"

    rows = [[v["mode"], "own" if v["own_stages"] else "all (before)", "yes" if v["completer_loaded"] else "no",
             ms(v, "complete_ms"), ms(v, "filter_ms"), f"{sum(v['stage_median_ms'].values()):.1f} ms",
             f"{v['rss_loaded_mb']:.0f} / {v['rss_peak_mb']:.0f} MB"] for v in d["variants"]]
    same = {mode: len({v["outputs_sha256"] for v in d["variants"] if v["mode"] == mode}) == 1
            for mode in dict.fromkeys(v["mode"] for v in d["variants"])}
    checked = "; ".join(f"{mode} node: published outputs {'equal' if ok else '**differ**'} both ways"
                        for mode, ok in same.items())
    header = ["node", "stages", "network loaded", "complete", "filter", "total (stage medians; lower is better)",
              "RSS loaded / peak"]
    return [*table(header, rows), "", f"{checked}."]


FIGURES: dict[str, Figure] = {
    "bench-startup": one("bench-startup", render_startup),
    "bench-nodes": one("bench-nodes", render_nodes),
}
