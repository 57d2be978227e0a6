"""Returned checkpoints against the shipped ones, from the runs `scripts/gpu_eval.sh` left in OUTDIR,
and whether each backend's new weights pass the ship gate.

    python scripts/gpu_compare.py OUTDIR

The gate (per learned backend; every clause must hold to ship):

* on the real frames, labelled boxes and PointRCNN's boxes (`real_*.json`, `real_det_*.json`): the
  lateral balance and the generated-only completeness of the generated points improve, the published
  completeness is not worse by more than ``PUBLISHED_SLACK``, the consistency is not worse;
* on SynthCars' held-out families (`fam_gen_*.json`, `fam_pub_*.json`: true shapes) and through
  `pcc demo` (`demo_SEED_BACKEND_*/demo.json`: the simulated detector's boxes) the CD-L1 is not
  worse by more than ``SYNTH_SLACK`` (overall, each family, each demo seed).

Why both real box sources: a completion balanced about the box's centre plane carries a detector's
box error onto the far flank; labelled boxes alone hide that. Why SynthCars and the demo: the real
reference is an aggregate of one seen flank, so only true shapes score the far side itself.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

BACKENDS = ("pointpncnet", "trapcc", "aml")
#: Published completeness may worsen this much (relative) on the real frames.
PUBLISHED_SLACK = 0.02
#: CD-L1 on true shapes may worsen this much (relative) before it counts as materially worse.
SYNTH_SLACK = 0.02
#: The real figures reported on the mean of the original and the mirrored frames (gpu_eval.sh step 6).
MIRROR_KEYS = ("completeness", "generated_completeness", "lateral_balance", "consistency")


def _load(path: Path) -> dict[str, Any]:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise SystemExit(f"{path}: {exc} (run scripts/gpu_eval.sh first)") from exc


def _summary(outdir: Path, run: str, which: str) -> dict[str, dict[str, float]]:
    return {r["backend"]: r for r in _load(outdir / f"{run}_{which}.json")["summary"]}


def _orientation_mean(outdir: Path, run: str, which: str, backend: str) -> dict[str, float]:
    """:data:`MIRROR_KEYS` of ``backend`` averaged over a real run and its mirrored run."""
    frames, mirrored = (_summary(outdir, name, which)[backend] for name in (run, f"{run}_mirror"))
    return {k: (frames[k] + mirrored[k]) / 2 for k in MIRROR_KEYS}


def _demo_cd(outdir: Path, backend: str, which: str) -> dict[int, float]:
    out = {}
    for path in sorted(outdir.glob(f"demo_*_{backend}_{which}/demo.json")):
        seed = int(path.parent.name.split("_")[1])
        out[seed] = _load(path)["synthcars"]["completion"][0]["cd_l1"]
    return out


def _change(old: float, new: float) -> str:
    return f"{old:.3f} → {new:.3f} ({100 * (new / old - 1):+.1f} %)" if old else f"{old:.3f} → {new:.3f}"


def compare(outdir: Path, backend: str) -> tuple[list[str], list[str]]:
    """The lines comparing ``backend``'s shipped and new runs, and the gate's failed clauses."""
    lines, failed = [], []
    for run, label in (("real", "real, labelled boxes"), ("real_det", "real, PointRCNN boxes")):
        old, new = (_summary(outdir, run, w)[backend] for w in ("shipped", "new"))
        keys = ("completeness", "generated_completeness", "lateral_balance", "consistency", "completeness_sym",
                "far_completeness_sym")
        lines.append(f"{label}: " + "; ".join(f"{k} {_change(old[k], new[k])}" for k in keys))
        for k in ("lateral_balance", "generated_completeness"):
            if new[k] >= old[k]:
                failed.append(f"{label}: {k} does not improve ({_change(old[k], new[k])})")
        if new["completeness"] > old["completeness"] * (1 + PUBLISHED_SLACK):
            failed.append(f"{label}: published completeness worse by more than {PUBLISHED_SLACK:.0%} "
                          f"({_change(old['completeness'], new['completeness'])})")
        if new["consistency"] > old["consistency"]:
            failed.append(f"{label}: consistency worse ({_change(old['consistency'], new['consistency'])})")
    for kind, label in (("gen", "SynthCars families, generated points"), ("pub", "SynthCars families, published")):
        old, new = (_load(outdir / f"fam_{kind}_{w}.json")["backends"][backend] for w in ("shipped", "new"))
        if not old["by_family"] or old["by_family"].keys() != new["by_family"].keys():
            raise SystemExit(f"{outdir}/fam_{kind}_*.json: the runs do not hold the same vehicle families "
                             "(pcc eval found no SynthCars meta.json?): the per-family clauses cannot be judged")
        parts = {"all": (old["overall"]["cd_l1"], new["overall"]["cd_l1"])}
        parts.update({f: (old["by_family"][f]["cd_l1"], new["by_family"][f]["cd_l1"]) for f in old["by_family"]})
        lines.append(f"{label}, CD-L1: " + "; ".join(f"{f} {_change(*v)}" for f, v in parts.items()))
        o, n = old["overall"], new["overall"]
        lines.append(f"{label}: lateral balance {_change(o['lateral_offset'], n['lateral_offset'])}; unseen half "
                     f"{_change(o['far_coverage'], n['far_coverage'])}; consistency "
                     f"{_change(o['consistency'], n['consistency'])}")
        failed += [f"{label}: CD-L1 {f} {_change(*v)}" for f, v in parts.items() if v[1] > v[0] * (1 + SYNTH_SLACK)]
    for run, label in (("real", "labelled boxes"), ("real_det", "PointRCNN boxes")):  # beside the gate
        if all((outdir / f"{run}_mirror_{w}.json").is_file() for w in ("shipped", "new")):
            old, new = (_orientation_mean(outdir, run, w, backend) for w in ("shipped", "new"))
            lines.append(f"real, {label}, mean of the frames and their mirror images (not in the gate): "
                         + "; ".join(f"{k} {_change(old[k], new[k])}" for k in MIRROR_KEYS))
    old, new = _demo_cd(outdir, backend, "shipped"), _demo_cd(outdir, backend, "new")
    seeds = sorted(old.keys() & new.keys())
    lines.append("pcc demo, CD-L1: " + "; ".join(f"seed {s} {_change(old[s], new[s])}" for s in seeds))
    failed += [f"pcc demo seed {s}: CD-L1 {_change(old[s], new[s])}" for s in seeds
               if new[s] > old[s] * (1 + SYNTH_SLACK)]
    return lines, failed


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("outdir", type=Path, help="the OUTDIR of scripts/gpu_eval.sh")
    args = parser.parse_args(argv)
    if not (args.outdir / "real_new.json").is_file():
        raise SystemExit(f"{args.outdir}: no real_new.json (run scripts/gpu_eval.sh first)")
    for backend in BACKENDS:
        if not list(args.outdir.glob(f"demo_*_{backend}_new")):  # gpu_eval.sh demos returned checkpoints only
            print(f"== {backend}: no returned checkpoint scored in {args.outdir}")
            continue
        lines, failed = compare(args.outdir, backend)
        print(f"== {backend}: {'ship' if not failed else 'keep the shipped weights'}")
        print("\n".join(f"  {line}" for line in lines))
        print("\n".join(f"  FAILS {why}" for why in failed) or "  every clause of the gate holds")
    return 0


if __name__ == "__main__":
    sys.exit(main())
