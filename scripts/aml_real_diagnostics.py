"""Where AML's real-scan error comes from: the measurements of docs/aml.md, one command::

    python scripts/aml_real_diagnostics.py --old-checkpoint OLD/aml.safetensors \\
        --caches out/data/kitti_tracking,out/data/kitti_object,out/data/nuscenes,out/data/cache

On the real KITTI tracking observations of ``pcc eval --real`` (labelled boxes, each track's
aggregated crops as partial ground truth) it prints, for the shipped AML weights (and the
``--old-checkpoint`` ones when given):

1. box proportions of each track and the 1st / 99th percentiles of its aggregated GT and of
   AML's completions in box units (does the completion fill the box?), and the spread of the
   completions' canonical extents over all observations (does every car come out alike?);
2. the sensor height above the box bottom of every instance cache in ``--caches`` (is the
   canonical sensor origin, from which free space is cast, where the LiDAR is?);
3. completeness by region of the box (rear / front face, sides, top) at 2048 and 16384
   output points (how much is shape, how much is point spacing), over all observations and
   per track;
4. on two observations, the ML baseline run to convergence at lambda 0 and at the
   checkpoint's lambda against the amortized encoder: code norm, observed-voxel NLL and
   completeness (the prior's shape space vs the amortization gap);
5. on the same observations, z fitted by ML to the track's whole aggregated GT (all of it
   observed) against the completer's own code of the crop (the encoder's, refined when the
   checkpoint or ``--refine-steps`` sets it), by region of the box: can the prior's shape
   space hold this car at all (the best its decoder can do), or does the encoder not ask for it?
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def _report_extents(name, completer, instances, contexts) -> None:
    from pcc_ros.geometry.voxels import box_aspect

    outs = completer.complete([i["partial"] for i in instances], contexts)
    tracks = sorted({i["key"].split("@")[0] for i in instances})
    for track in tracks:  # a handful of tracks
        idx = [j for j, i in enumerate(instances) if i["key"].split("@")[0] == track]
        size = instances[idx[0]]["size"]
        gt = instances[idx[0]]["reference"] / box_aspect(size)
        box = [outs[j] / box_aspect(instances[j]["size"]) for j in idx]
        print(f"  {name} {track}: box l w h {np.round(size, 2)} (h/l {size[2] / size[0]:.3f}); box units p1/p99: "
              f"GT {np.percentile(gt, 1, 0).round(3)} {np.percentile(gt, 99, 0).round(3)}, completion "
              f"{np.mean([np.percentile(b, 1, 0) for b in box], 0).round(3)} "
              f"{np.mean([np.percentile(b, 99, 0) for b in box], 0).round(3)}")
    extent = np.array([np.percentile(o, 99, 0) - np.percentile(o, 1, 0) for o in outs])
    height = np.mean([e[2] * i["size"][0] / i["size"][2] for e, i in zip(extent, instances)])
    print(f"  {name}: completion extent (canonical) mean {extent.mean(0).round(3)}, std over instances "
          f"{extent.std(0).round(4)}; height / box height {height:.3f}")


def _regions(box_points):
    """Masks of the box regions (box units): rear / front face, sides, top."""
    return {"rear face": box_points[:, 0] < -0.4, "front face": box_points[:, 0] > 0.4,
            "sides": np.abs(box_points[:, 1]) > 0.4, "top": box_points[:, 2] > 0.3}


def _report_regions(name, completer, instances, contexts, counts) -> None:
    """Completeness by box region over all observations, then per track (2048 points and more)."""
    from scipy.spatial import cKDTree

    from pcc_ros.geometry.voxels import box_aspect

    tracks = sorted({i["key"].split("@")[0] for i in instances})
    for n in counts:
        completer.config["output_points"] = n
        outs = completer.complete([i["partial"] for i in instances], contexts)
        sums: dict[str, dict[str, list[float]]] = {}
        means: dict[str, list[float]] = {}
        for o, inst in zip(outs, instances):  # 35 instances, vectorised inside
            d = cKDTree(o).query(inst["reference"])[0] * inst["size"][0]
            b = inst["reference"] / box_aspect(inst["size"])
            regions = _regions(b)
            regions["rest"] = ~np.any(list(regions.values()), axis=0)
            for group in ("all", inst["key"].split("@")[0]):
                means.setdefault(group, []).append(d.mean())
                for k, m in regions.items():
                    cell = sums.setdefault(group, {}).setdefault(k, [0.0, 0.0])
                    cell[0] += float(d[m].sum())
                    cell[1] += float(m.sum())
        for group in ("all", *tracks):
            total = sum(c for _, c in sums[group].values())
            parts = ", ".join(f"{k} {s / max(c, 1):.3f} m ({100 * c / total:.0f} % of GT)"
                              for k, (s, c) in sums[group].items())
            print(f"  {name}, {n} points, {group} ({len(means[group])} obs.): completeness "
                  f"{np.mean(means[group]):.4f} m; by region: {parts}")
    completer.config["output_points"] = 2048


def _report_oracle(completer, instances, contexts, keys, steps) -> None:
    import torch
    from scipy.spatial import cKDTree

    from pcc_ros.geometry.voxels import box_aspect

    picks = [j for j, i in enumerate(instances) if i["key"].split(":", 1)[-1] in keys]
    crops = [instances[j]["partial"] for j in picks]
    with torch.inference_mode():
        whole, aspects = completer.observe([instances[j]["reference"] for j in picks], [contexts[j] for j in picks])
        crop, _ = completer.observe(crops, [contexts[j] for j in picks])
        encoded = completer.decode_points(completer.model.decoder(completer.latent_codes(crop)), crops, aspects)
    z = completer.fit_latent(whole[:, 0] > 0.5, whole[:, 1] > 0.5, steps=steps)
    with torch.inference_mode():
        fitted = completer.decode_points(completer.model.decoder(z), crops, aspects)
    mine = f"encoder{f' + {completer.refine_steps} refine steps' if completer.refine_steps else ''} on the crop"
    for label, outs in ((mine, encoded), (f"ML on the whole GT, {steps} steps", fitted)):
        for j, o in zip(picks, outs):
            inst = instances[j]
            d = cKDTree(o).query(inst["reference"])[0] * inst["size"][0]
            parts = " ".join(f"{k} {d[m].mean():.3f} m ({100 * m.mean():.0f} %)"
                             for k, m in _regions(inst["reference"] / box_aspect(inst["size"])).items() if m.any())
            print(f"  {label} {inst['key']}: completeness {d.mean():.3f} m; {parts}")


def _report_amortization(completer, instances, contexts, keys, steps) -> None:
    import torch
    from scipy.spatial import cKDTree

    from pcc_ros.models.aml import observed_nll

    picks = [j for j, i in enumerate(instances) if i["key"].split(":", 1)[-1] in keys]
    clouds = [instances[j]["partial"] for j in picks]
    with torch.inference_mode():
        x, aspects = completer.observe(clouds, [contexts[j] for j in picks])
    occ, free = x[:, 0] > 0.5, x[:, 1] > 0.5
    log_var = float(completer.config["log_var"])

    def show(label, z):
        with torch.inference_mode():
            decoded = completer.model.decoder(z)
            nll = observed_nll(decoded, occ, free, log_var)
            outs = completer.decode_points(decoded, clouds, aspects)
        for j, o, n, zz in zip(picks, outs, nll, z):
            inst = instances[j]
            comp = cKDTree(o).query(inst["reference"])[0].mean() * inst["size"][0]
            print(f"  {label} {inst['key']}: |z| {float(zz.norm()):.2f}, observed-voxel NLL {float(n):.0f}, "
                  f"completeness {comp:.3f} m")

    with torch.inference_mode():
        show("amortized encoder", completer.model.encoder(x))
    for lam in (0.0, completer.lam):
        show(f"ML lambda {lam:g}, {steps} steps", completer.fit_latent(occ, free, steps=steps, lam=lam))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--real-sources", default="../shared/data/kitti_tracking")
    parser.add_argument("--checkpoint", type=Path, help="AML weights (default: the shipped ones)")
    parser.add_argument("--old-checkpoint", type=Path, help="other AML weights to compare (e.g. the first ones)")
    parser.add_argument("--caches", default="", help="comma-separated instance caches for the sensor-height check")
    parser.add_argument("--observations", default="0000/0@0,0000/3@19", help="observations of the ML check")
    parser.add_argument("--ml-steps", type=int, default=200)
    parser.add_argument("--refine-steps", type=int, help="refine the encoder's codes (default: the checkpoint's)")
    parser.add_argument("--sections", default="1,2,3,4,5", help="comma-separated sections to run (numbers above)")
    args = parser.parse_args()
    sections = {int(s) for s in args.sections.split(",") if s}

    import torch

    from pcc_ros.data.instance_cache import InstanceCache
    from pcc_ros.models import load_completer
    from pcc_ros.workflows.evaluate_real import real_instances, scene_contexts

    torch.set_num_threads(1)
    instances, _ = real_instances([Path(s) for s in args.real_sources.split(",") if s])
    contexts = scene_contexts(instances)
    models = {"shipped": load_completer("aml", args.checkpoint, device="cpu", refine_steps=args.refine_steps)}
    if args.old_checkpoint:
        models["old"] = load_completer("aml", args.old_checkpoint, device="cpu")
    print(f"{len(instances)} real observations")
    if 1 in sections:
        print("1. box vs completion extents")
        for name, model in models.items():
            _report_extents(name, model, instances, contexts)
    if 2 in sections:
        print("2. sensor height above the box bottom (median, metres)")
        for path in [c for c in args.caches.split(",") if c]:
            meta = InstanceCache.load(path).meta
            height = meta["origin"][:, 2] * meta["box_size"][:, 0] + meta["box_size"][:, 2] / 2
            print(f"  {path}: {np.median(height):.2f} m over {len(height)} instances")
    if 3 in sections:
        print("3. completeness by region of the box")
        for name, model in models.items():
            _report_regions(name, model, instances, contexts, (2048, 16384))
    if 4 in sections:
        print("4. amortized encoder vs ML to convergence (shipped weights)")
        _report_amortization(models["shipped"], instances, contexts, args.observations.split(","), args.ml_steps)
    if 5 in sections:
        print("5. the prior's best fit to the whole aggregated GT vs the encoder on the crop (shipped weights)")
        _report_oracle(models["shipped"], instances, contexts, args.observations.split(","), args.ml_steps)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
