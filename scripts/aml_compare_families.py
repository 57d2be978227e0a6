"""Paired per-car comparison of AML checkpoints on a SynthCars families cache: for each family,
the mean change of CD-L1 (generated points, metres) against the shipped weights, with a 95 %
interval of the paired differences (the ship gate's "families not worse beyond noise")::

    python scripts/aml_compare_families.py RUN/aml.safetensors [MORE.safetensors ...] \\
        --data data/fam_cache --max-instances 350

Run it where the cache's SynthCars root (its ``index.json`` ``synthcars``) resolves, so the
instances carry their families.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("checkpoints", nargs="+", type=Path)
    parser.add_argument("--data", type=Path, default=Path("data/fam_cache"))
    parser.add_argument("--split", default="test")
    parser.add_argument("--max-instances", type=int, default=350)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    import torch

    from pcc_ros.data.instance_cache import InstanceCache
    from pcc_ros.models import load_completer
    from pcc_ros.workflows.evaluate import instances_from_cache, score_backend

    torch.set_num_threads(1)
    instances, _ = instances_from_cache(InstanceCache.load(args.data), args.split, args.max_instances, args.seed,
                                        "ground_truth")
    family = np.array([str(i.meta.get("family", "")) for i in instances])
    lengths = np.array([i.length for i in instances])

    def cd_l1(checkpoint: Path | None) -> np.ndarray:
        completer = load_completer("aml", checkpoint, device="cpu", decode_density=2)
        _, rows, _ = score_backend(completer, instances, seed=args.seed, with_emd=False, progress=False)
        return np.array([r["cd_l1"] for r in rows]) * lengths

    shipped = cd_l1(None)
    for checkpoint in args.checkpoints:  # a handful of candidates
        diff = cd_l1(checkpoint) - shipped
        cells = []
        for f in sorted(set(family)):  # seven families
            m = family == f
            half = 1.96 * diff[m].std() / np.sqrt(m.sum())
            cells.append(f"{f or '?'} {100 * diff[m].mean() / shipped[m].mean():+.1f} % "
                         f"(±{100 * half / shipped[m].mean():.1f}, n {m.sum()})")
        print(f"{checkpoint}: " + ", ".join(cells) + f"; overall {100 * diff.mean() / shipped.mean():+.1f} %")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
