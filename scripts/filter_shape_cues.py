"""Cheap geometric shape cues of a car body against a blob, a bush, a wall or a bin, measured.

Diagnosis only (numpy, per box): for every detection of a SynthCars calibration root (the seed-11
sets; never a held-out seed) the shipped rule judges it as the node does (``sensor: auto``), and
each candidate cue is measured in the box frame. Printed per sensor: each cue's AUC of the
confusions above the true cars, of the confusions the shipped rule keeps above the true cars it
keeps, and per object under the kept confusions. A cue reads higher on a false box (its sign is
chosen so). Candidates:

* ``corner_pass``: rays through the box's four vertical corner columns (outer ``A_LEN`` of the
  length by outer ``A_WID`` of the width, ``CORNER_Z`` of the height) that return from beyond
  the column, as a share of those that cross it and end beyond its entry (pass + stop, with
  ``PRIOR`` prior stops). A car's body fills its box's corners; an ellipsoid leaves them air.
* ``corner_share``: 1 - the share of the mid-height returns (20-70 % of the height) lying in
  those corner columns (with prior returns at a car's share).
* ``face_dist``: mean BEV distance of the mid-height returns to the box rectangle's boundary,
  metres (a car's returns lie on its faces; an ellipsoid's curve away at the ends).
* ``extent``: 1 - max(length extent, width extent) of the returns (5-95 % quantiles, shares of
  the box's), a bin or bush covers a part of its box.
* ``end_low``: mid-third highest return minus the end thirds' (shares of the height).

    PYTHONPATH=$PWD python scripts/filter_shape_cues.py data/synthcars_sensors_8x20 --seed 11
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from pcc_ros.data.synthetic.writer import read_kinds
from pcc_ros.geometry.canonical import to_box_local
from pcc_ros.pipeline.evidence import angular_window
from pcc_ros.workflows.detection_eval import auc, build_pipeline
from pcc_ros.workflows.filter_sensors import judged_synth_frames

A_LEN, A_WID, CORNER_Z = 0.2, 0.3, (0.25, 0.65)
PRIOR = 2.0
CUES = ("corner_pass", "corner_share", "face_dist", "extent", "end_low")


def corner_regions(half: np.ndarray, a_len: float, a_wid: float, zband) -> tuple[np.ndarray, np.ndarray]:
    """The four corner columns' (lo, hi) corners in the box frame (centre at 0)."""
    hx, hy, hz = half
    lo, hi = [], []
    for sx in (-1, 1):
        for sy in (-1, 1):
            xs = sorted((sx * hx, sx * hx * (1 - 2 * a_len)))
            ys = sorted((sy * hy, sy * hy * (1 - 2 * a_wid)))
            lo.append([xs[0], ys[0], -hz + zband[0] * 2 * hz])
            hi.append([xs[1], ys[1], -hz + zband[1] * 2 * hz])
    return np.array(lo), np.array(hi)


def cues_of_box(pts_local: np.ndarray, origin: np.ndarray, half: np.ndarray, variants) -> dict[str, float]:
    """Every cue of one box from the candidate returns in its frame (rays from ``origin``)."""
    out = {}
    d = pts_local - origin
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        for name, (a_len, a_wid, zb) in variants.items():
            lo, hi = corner_regions(half, a_len, a_wid, zb)
            t0 = (lo[None] - origin) * inv[:, None]
            t1 = (hi[None] - origin) * inv[:, None]
            tin = np.nanmax(np.minimum(t0, t1), axis=2)
            tout = np.nanmin(np.maximum(t0, t1), axis=2)
            hit = tout >= np.maximum(tin, 0)
            passed = (hit & (tout < 1.0)).any(axis=1)
            stop = (hit & (tin <= 1.0) & (tout >= 1.0)).any(axis=1)
            npass, nstop = float(passed.sum()), float(stop.sum())
            out[name] = (npass) / (npass + nstop + PRIOR)
    hx, hy, hz = half
    inside = (np.abs(pts_local[:, 0]) <= hx + 0.1) & (np.abs(pts_local[:, 1]) <= hy + 0.1)
    h = (pts_local[:, 2] + hz) / (2 * hz)
    body = inside & (h >= 0.2) & (h <= 1.0)
    mid = body & (h <= 0.7)
    p = pts_local[mid]
    n = len(p)
    u, v = np.abs(p[:, 0]) / hx, np.abs(p[:, 1]) / hy
    corner = (u >= 1 - 2 * A_LEN) & (v >= 1 - 2 * A_WID)
    out["corner_share"] = 1.0 - (corner.sum() + 0.4 * 10) / (n + 10)
    for name, (al, aw, zb) in SHARE_VARIANTS.items():
        sel = inside & (h >= zb[0]) & (h <= zb[1])
        uu, vv = np.abs(pts_local[sel, 0]) / hx, np.abs(pts_local[sel, 1]) / hy
        out[f"n_{name}"] = float(sel.sum())
        out[f"c_{name}"] = float(((uu >= 1 - 2 * al) & (vv >= 1 - 2 * aw)).sum())
    dist = np.minimum(np.maximum(hx - np.abs(p[:, 0]), 0), np.maximum(hy - np.abs(p[:, 1]), 0))
    out["face_dist"] = (dist.sum() + 0.05 * 10) / (n + 10)
    b = pts_local[body]
    if len(b) >= 5:
        ex = (np.quantile(b[:, 0], 0.95) - np.quantile(b[:, 0], 0.05)) / (2 * hx)
        ey = (np.quantile(b[:, 1], 0.95) - np.quantile(b[:, 1], 0.05)) / (2 * hy)
        out["extent"] = 1.0 - max(ex, ey)
        third = np.digitize(b[:, 0], [-hx / 3, hx / 3])
        tops = [b[third == k, 2].max() if (third == k).any() else np.nan for k in range(3)]
        ends = np.nanmean([tops[0], tops[2]]) if np.isfinite([tops[0], tops[2]]).any() else np.nan
        out["end_low"] = -((tops[1] - ends) / (2 * hz)) if np.isfinite(tops[1]) and np.isfinite(ends) else 0.0
    else:
        out["extent"] = 0.0
        out["end_low"] = 0.0
    return out


SHARE_VARIANTS = {"a": (0.2, 0.3, (0.2, 0.7)), "b": (0.15, 0.25, (0.2, 0.7)), "c": (0.25, 0.35, (0.2, 0.7)),
                  "d": (0.2, 0.3, (0.2, 1.0)), "e": (0.2, 0.3, (0.0, 0.7)), "f": (0.3, 0.3, (0.2, 0.7)),
                  "g": (0.2, 0.4, (0.2, 0.7)), "h": (0.1, 0.2, (0.2, 0.7))}
VARIANTS = {"corner_pass": (A_LEN, A_WID, CORNER_Z), "corner_pass_s": (0.15, 0.25, CORNER_Z),
            "corner_pass_l": (0.3, 0.35, CORNER_Z), "corner_pass_h": (A_LEN, A_WID, (0.2, 0.8))}


def measure(root: Path, layout: str, rays: bool = True) -> dict[str, np.ndarray]:
    pipeline = build_pipeline(None, {"backend": "input", "sensor": "auto"})
    det_root = root / "detections" / "synthetic"
    cols: dict[str, list] = {}
    for f, boxes, r in judged_synth_frames(pipeline, root, layout):
        _, objects = read_kinds(det_root / f"{f.name}.kind", len(boxes))
        pts = np.asarray(f.points[:, :3], dtype=np.float64)
        az = np.arctan2(pts[:, 1], pts[:, 0])
        az_lo, az_hi, *_ = angular_window(boxes)
        cos, sin = np.cos(boxes.yaw), np.sin(boxes.yaw)
        for b in range(len(boxes)):
            c = boxes.center[b]
            rel = (az - (az_lo[b] + az_hi[b]) / 2 + np.pi) % (2 * np.pi) - np.pi
            sel = np.abs(rel) <= (az_hi[b] - az_lo[b]) / 2 + 0.002
            q = pts[sel]
            x, y, z = to_box_local(q[:, 0], q[:, 1], q[:, 2], c[0], c[1], c[2], cos[b], sin[b])
            o = np.array(to_box_local(0.0, 0.0, 0.0, c[0], c[1], c[2], cos[b], sin[b]))
            row = cues_of_box(np.stack([x, y, z], 1), o, boxes.size[b] / 2, VARIANTS if rays else {})
            row.update(kind=f.kinds[b], obj=objects[b], kept=r.status[b] != "rejected", p=r.filter_score[b],
                       range=float(np.hypot(c[0], c[1])), n_in=r.filter_terms["n_in"][b])
            for k, val in row.items():
                cols.setdefault(k, []).append(val)
    return {k: np.array(v) for k, v in cols.items()}


def report(layout: str, m: dict[str, np.ndarray]) -> dict:
    true = m["kind"] == "true"
    conf = m["kind"] == "confusion"
    kept = m["kept"].astype(bool)
    names = [k for k in m if k.startswith("corner_pass")] + [c for c in CUES[1:] if c in m]
    res = {}
    print(f"\n## {layout}: true {true.sum()}, confusions {conf.sum()} (kept {(conf & kept).sum()})")
    objs = sorted(set(m["obj"][conf & kept]))
    heads = [f"kept {o} ({(conf & kept & (m['obj'] == o)).sum()})" for o in objs]
    print("| cue | conf vs true | kept conf vs kept true | " + " | ".join(heads) + " |")
    for c in names:
        x = m[c].astype(float)

        def a(sel_false, sel_true, x=x):
            s = sel_false | sel_true
            return auc(x[s], sel_true[s]) if sel_false.any() and sel_true.any() else float("nan")

        row = [a(conf, true), a(conf & kept, true & kept)]
        row += [a(conf & kept & (m["obj"] == o), true & kept) for o in objs]
        res[c] = row
        print(f"| {c} | " + " | ".join(f"{v:.3f}" for v in row) + " |")
    return res


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("root", type=Path)
    parser.add_argument("--seed", type=int, default=11)
    parser.add_argument("--sensors", default="hdl64,vlp16,vlp32c,os1_64")
    parser.add_argument("--save", type=Path, default=None, help="npz of the measured rows per sensor")
    parser.add_argument("--no-rays", action="store_true", help="leave out the ray-traced corner_pass variants")
    args = parser.parse_args()
    allres = {}
    for layout in args.sensors.split(","):
        m = measure(args.root / f"{layout}_s{args.seed}", layout, not args.no_rays)
        if args.save:
            args.save.mkdir(parents=True, exist_ok=True)
            np.savez(args.save / f"{layout}.npz", **m)
        allres[layout] = report(layout, m)
    print(json.dumps(allres))


if __name__ == "__main__":
    main()
