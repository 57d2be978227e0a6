"""Which false boxes the shipped filter keeps on SynthCars, and what the scan says of them.

For every simulated sensor of a calibration root (``pcc calibrate-filter --sim-root``; the
seed-11 sets, never a held-out seed), the shipped rule judges every detection as the node does
(``sensor: auto``, the beam model estimated afresh per sequence) and this prints, per sensor and
false-positive kind, for the kept false boxes against the true cars: their range, returns, how
many rings of the sensor's table cross the core band and the body, the rays through the core,
``free_space`` and how many boxes the scan cannot judge at all (no ray reaches the box body
unobstructed: every ray towards it ended in front of it, or none came). ``--core-open F`` and
``--cabin F``: the core's top and length where no ring crosses the band
(:data:`pcc_ros.pipeline.evidence.CORE_Z_OPEN`, :data:`~pcc_ros.pipeline.evidence.CABIN_FRACTION`;
``--core-open 0.6 --cabin 0.8`` is the rule before the sparse-ring core), the weights as configured
(``--config``: another rule file).

    PYTHONPATH=$PWD python scripts/filter_kept_false.py data/synthcars_sensors_8x20 --seed 11
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from pcc_ros.data.synthetic.writer import read_kinds
from pcc_ros.geometry.beams import SENSOR_PRESETS
from pcc_ros.pipeline import evidence as ev
from pcc_ros.workflows.detection_eval import build_pipeline
from pcc_ros.workflows.filter_sensors import judged_synth_frames

#: The terms the per-object table prints (medians), besides the raw counts.
DIAG_TERMS = ("density", "free_space", "ground_gap", "depth", "above", "overlap", "cover", "corner", "top", "spill",
              "fill")
#: The objects the kept confusions mostly sit on (the rest pooled as "other").
MAIN_OBJECTS = ("blob", "bush", "low_wall", "bin", "tree")


def measure(root: Path, layout: str, config: Path | None = None) -> dict[str, np.ndarray]:
    """Per detection of the set: kind, kept, raw counts, terms, range, ring crossings."""
    pipeline = build_pipeline(config, {"backend": "input", "sensor": "auto"})
    cols: dict[str, list] = {}
    preset = SENSOR_PRESETS[layout]
    det_root = root / "detections" / "synthetic"
    for f, boxes, r in judged_synth_frames(pipeline, root, layout):
        t = r.filter_terms
        row = {"kind": f.kinds, "kept": r.status != "rejected", "p": r.filter_score,
               "range": np.hypot(boxes.center[:, 0], boxes.center[:, 1]),
               "core_rings": ev.core_rings(boxes, preset),
               "body_rings": ev.core_rings(boxes, preset, (ev.CORE_Z[0], 1.0))}
        kinds = read_kinds(det_root / f"{f.name}.kind", len(boxes))
        row["obj"] = kinds[1] if kinds is not None else np.full(len(boxes), "-", dtype=object)
        for k in ("n_in", "n_pass", "n_stop", "n_rays", "n_occluded", "expected", *DIAG_TERMS):
            if k in t:
                row[k] = t[k]
        for k, v in row.items():
            cols.setdefault(k, []).append(np.asarray(v))
    return {k: np.concatenate(v) for k, v in cols.items()}


def report(layout: str, m: dict[str, np.ndarray]) -> None:
    true = m["kind"] == "true"
    print(f"\n## {layout}: true cars {true.sum()}, lost {(~m['kept'][true]).mean():.1%}")
    print("| boxes | n | range m (median) | returns (median) | 0 returns | no core ring | no body ring "
          "| core rays (pass+stop, median) | no core ray | free_space 0 | unjudgeable (no unobstructed ray) |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")

    def line(name: str, sel: np.ndarray) -> None:
        if not sel.any():
            return
        core = m["n_pass"][sel] + m["n_stop"][sel]
        blind = (m["n_rays"][sel] - m["n_occluded"][sel]) == 0
        print(f"| {name} | {sel.sum()} | {np.median(m['range'][sel]):.0f} | {np.median(m['n_in'][sel]):.0f} | "
              f"{(m['n_in'][sel] == 0).mean():.0%} | {(m['core_rings'][sel] == 0).mean():.0%} | "
              f"{(m['body_rings'][sel] == 0).mean():.0%} | {np.median(core):.0f} | {(core == 0).mean():.0%} | "
              f"{(m['free_space'][sel] == 0).mean():.0%} | {blind.mean():.0%} ({blind.sum()}) |")

    line("true, all", true)
    line("true, kept", true & m["kept"])
    for kind in ("confusion", "misplaced", "far", "ghost"):
        sel = m["kind"] == kind
        if sel.any():
            print(f"| *{kind}: removed {(~m['kept'][sel]).mean():.1%} of {sel.sum()}* | | | | | | | | | | |")
            line(f"{kind}, all", sel)
            line(f"{kind}, kept", sel & m["kept"])


def by_object(layout: str, m: dict[str, np.ndarray]) -> None:
    """The confusions the rule keeps, per object they sit on: counts, how many are evidence-poor
    (fewer than 5 returns, or no ray through the core), and the median terms, range, returns and
    visibility against the kept true cars'."""
    true, conf, kept = m["kind"] == "true", m["kind"] == "confusion", m["kept"].astype(bool)
    terms = [k for k in DIAG_TERMS if k in m]
    visible = np.where(m["n_rays"] > 0, 1.0 - m["n_occluded"] / np.maximum(m["n_rays"], 1.0), 1.0)
    print(f"\n## {layout}: confusions {conf.sum()}, kept {(conf & kept).sum()}")
    print("| boxes | n (kept / all) | evidence-poor | range | returns | visible | " + " | ".join(terms) + " |")
    print("| --- " * (6 + len(terms)) + "|")

    def line(name: str, sel: np.ndarray, total: int) -> None:
        if not sel.any():
            return
        poor = (m["n_in"][sel] < 5) | ((m["n_pass"][sel] + m["n_stop"][sel]) == 0)
        med = [np.median(m[k][sel]) for k in terms]
        print(f"| {name} | {sel.sum()} / {total} | {poor.sum()} | {np.median(m['range'][sel]):.0f} | "
              f"{np.median(m['n_in'][sel]):.0f} | {np.median(visible[sel]):.2f} | "
              + " | ".join(f"{v:.2f}" for v in med) + " |")

    line("true, kept", true & kept, int(true.sum()))
    line("confusion, kept", conf & kept, int(conf.sum()))
    for obj in sorted(set(m["obj"][conf]), key=lambda o: -(conf & kept & (m["obj"] == o)).sum()):
        line(f"kept {obj}", conf & kept & (m["obj"] == obj), int((conf & (m["obj"] == obj)).sum()))
    line("confusion, removed", conf & ~kept, int(conf.sum()))


def pooled(measured: dict[str, dict[str, np.ndarray]]) -> None:
    """Kept / all confusions per layout and object, then the kept ones' medians over every layout."""
    print("\n| layout | confusions kept / all | " + " | ".join(MAIN_OBJECTS) + " | other | evidence-poor kept |")
    print("| --- " * (4 + len(MAIN_OBJECTS)) + "|")
    for layout, m in measured.items():
        conf, kept = m["kind"] == "confusion", m["kept"].astype(bool)
        poor = (m["n_in"] < 5) | ((m["n_pass"] + m["n_stop"]) == 0)
        cells = [conf & (m["obj"] == o) for o in MAIN_OBJECTS] + [conf & ~np.isin(m["obj"], MAIN_OBJECTS)]
        print(f"| {layout} | {(conf & kept).sum()} / {conf.sum()} | "
              + " | ".join(f"{(c & kept).sum()} / {c.sum()}" for c in cells) + f" | {(conf & kept & poor).sum()} |")
    m = {k: np.concatenate([v[k] for v in measured.values()]) for k in next(iter(measured.values()))}
    conf, kept, true = m["kind"] == "confusion", m["kept"].astype(bool), m["kind"] == "true"
    other = conf & kept & ~np.isin(m["obj"], MAIN_OBJECTS)
    by_object("all layouts pooled", m)
    print(f"(kept confusions on other objects: {other.sum()}; kept true cars: {(true & kept).sum()})")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("root", type=Path)
    parser.add_argument("--seed", type=int, default=11)
    parser.add_argument("--sensors", default="hdl64,vlp16,vlp32c,os1_64")
    parser.add_argument("--core-open", type=float, default=None)
    parser.add_argument("--cabin", type=float, default=None)
    parser.add_argument("--config", type=Path, default=None)
    parser.add_argument("--objects", action="store_true", help="the kept confusions per object they sit on")
    parser.add_argument("--save", type=Path, default=None, help="directory: the measured rows as <layout>.npz")
    args = parser.parse_args()
    if args.core_open is not None:
        ev.CORE_Z_OPEN = args.core_open
    if args.cabin is not None:
        ev.CABIN_FRACTION = args.cabin
    measured: dict[str, dict[str, np.ndarray]] = {}
    for layout in args.sensors.split(","):
        m = measure(args.root / f"{layout}_s{args.seed}", layout, args.config)
        if args.save:
            args.save.mkdir(parents=True, exist_ok=True)
            np.savez(args.save / f"{layout}.npz", **{k: v.astype(str) if v.dtype == object else v
                                                     for k, v in m.items()})
        report(layout, m)
        if args.objects:
            by_object(layout, m)
        measured[layout] = m
    if args.objects:
        pooled(measured)


if __name__ == "__main__":
    main()
