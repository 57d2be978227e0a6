"""Choose AML's ``refine_steps`` / ``refine_lr`` (the encoder's code refined by Eq. 4) on validation
data, as lambda is chosen: CD-L1 on SynthCars ``val`` instances and the held-out points of the real
training crops (never the real evaluation frames)::

    python scripts/aml_select_refinement.py --data data/cache --real out/data/kitti_object,out/data/nuscenes \\
        --steps 0,5,10,20 --lrs 0.05,0.15 --json out/refine_selection.json [--write RUN/aml.safetensors]

``--write`` records the chosen setting (``training.refine_steps`` / ``refine_lr``) and the tables
(``training.refine_selection``) in that checkpoint's JSON (the weights are untouched).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--checkpoint", type=Path, help="AML weights (default: the shipped ones)")
    parser.add_argument("--data", type=Path, default=Path("data/cache"), help="SynthCars instance cache")
    parser.add_argument("--split", default="val")
    parser.add_argument("--val-instances", type=int, default=96)
    parser.add_argument("--real", default="", help="comma-separated real instance caches (training-side crops)")
    parser.add_argument("--steps", default="0,5,10,20")
    parser.add_argument("--lrs", default="0.05,0.15")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", type=Path, help="write the selection here")
    parser.add_argument("--write", type=Path, help="record the choice in this checkpoint's JSON")
    args = parser.parse_args()

    import torch

    from pcc_ros import files
    from pcc_ros.data.instance_cache import InstanceCache
    from pcc_ros.models import load_completer
    from pcc_ros.models.aml import real_crops, select_refinement
    from pcc_ros.models.checkpoint import checkpoint_paths, load_config
    from pcc_ros.workflows.evaluate import instances_from_cache

    torch.set_num_threads(1)
    completer = load_completer("aml", args.checkpoint, device="cpu")
    instances, _ = instances_from_cache(InstanceCache.load(args.data), args.split, args.val_instances, args.seed,
                                        "ground_truth")
    real = real_crops([InstanceCache.load(p) for p in args.real.split(",") if p]) if args.real else None
    out = select_refinement(completer, instances, [int(s) for s in args.steps.split(",")],
                            [float(v) for v in args.lrs.split(",")], args.seed, real=real)
    out.update(data=str(args.data), split=args.split, real=args.real)
    print(json.dumps(out, indent=1))
    if args.json:
        files.write_json(args.json, out)
    if args.write:
        config = load_config(args.write)
        config["training"].update(refine_steps=out["refine_steps"], refine_lr=out["refine_lr"],
                                  refine_selection=out)
        files.write_json(checkpoint_paths(args.write)[1], config, indent=2, sort_keys=False)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
