"""Where a backend puts its points across the car: lean of density or a missing flank?

    python scripts/lateral_density.py --data CACHE [--split val] [--instances 120]
        [--backend trapcc] [--checkpoint W]

Completes ``--instances`` observations of an instance cache (SynthCars: true shapes) and prints, in
metres of the box frame: the generated points' mean lateral coordinate signed towards the flank the
sensor saw (and its absolute value, ``pcc eval``'s lateral balance), the share of points on the seen
flank, the 97th-percentile extent on each flank and the midpoint of the 3rd / 97th percentiles (a
car drawn off its box), then the raw mean in the box frame by the side the car was seen from (a
preference for one side of the frame whichever flank was seen). ``docs/trapcc.md`` ("Far side, a
density lean") reads TraPCC's shipped weights with it.
"""

from __future__ import annotations

import argparse

import numpy as np

from pcc_ros.data.instance_cache import InstanceCache
from pcc_ros.models import load_completer
from pcc_ros.workflows.evaluate import instances_from_cache, score_backend


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", required=True, help="an instance cache (pcc extract)")
    parser.add_argument("--split", default="val")
    parser.add_argument("--instances", type=int, default=120)
    parser.add_argument("--backend", default="trapcc")
    parser.add_argument("--checkpoint", default=None, help="default: the shipped weights")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    cache = InstanceCache.load(args.data)
    instances, reference = instances_from_cache(cache, args.split, args.instances, args.seed)
    completer = load_completer(args.backend, args.checkpoint, device="cpu")
    outputs, _, _ = score_backend(completer, instances, seed=args.seed, with_emd=False, progress=False)
    length = np.array([inst.length for inst in instances])
    seen = np.array([np.sign(inst.partial[:, 1].mean()) or 1.0 for inst in instances])  # +1: seen from +y
    y = [out[:, 1] * s for out, s in zip(outputs, seen)]  # towards the seen flank positive
    signed = np.array([v.mean() for v in y]) * length
    share = np.array([(v > 0).mean() for v in y])
    near, far = (np.array([np.percentile(v, 97) for v in y]) * length,
                 np.array([-np.percentile(v, 3) for v in y]) * length)
    middle = np.array([(np.percentile(v, 97) + np.percentile(v, 3)) / 2 for v in y]) * length
    raw = signed * seen
    print(f"{args.backend}, {len(instances)} observations of {args.data} ({args.split}, reference {reference}), "
          "metres:")
    print(f"  mean towards the seen flank {signed.mean():+.3f} (|mean| {np.abs(signed).mean():.3f}); share of points "
          f"on the seen flank {share.mean():.2f}; extent seen / far flank {near.mean():.2f} / {far.mean():.2f}; "
          f"extents' midpoint {middle.mean():+.3f}")
    print(f"  mean in the box frame {raw.mean():+.3f}: seen from +y {raw[seen > 0].mean():+.3f} "
          f"({(seen > 0).sum()}), from -y {raw[seen < 0].mean():+.3f} ({(seen < 0).sum()})")


if __name__ == "__main__":
    main()
