"""GPU completion throughput: each learned backend (shipped weights) on CUDA, float32 and
``half_precision``, against the CPU's default path, on the same clouds in one process.

For every backend: the CPU completer (its default inference path, the CPU's threads as
``--cpu-threads``), a CUDA float32 completer and a CUDA float16 completer are loaded from the
same weights. Their outputs on the batch are compared first: the largest Chamfer-L1 between a
cloud's completion and the CPU's (canonical frame; order-free, as AML samples its surface) must
stay under 5e-3 in float32 and 0.02 in float16. Then the three are timed
interleaved, round by round (``--repeat`` rounds after a warm-up; each GPU call ends with
``torch.cuda.synchronize`` inside ``complete``, as its output is copied back to the host), at every
``--batches`` size. Reported: min / median / max ms per batch and instances per second.

Where no CUDA device is present the benchmark says so and writes ``{"skipped": reason}``.
"""

from __future__ import annotations

import argparse
from typing import Any

import numpy as np

from benchmarks.common import interleaved, load_average, print_table, summary_ms
from benchmarks.complete import car_clouds, frame_contexts

#: Largest Chamfer-L1 from the CPU's float32 output each setting may show (canonical frame, where a
#: car's length is about 1).
TOLERANCE = {"cuda_fp32": 5e-3, "cuda_fp16": 0.02}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--backends", default="pointpncnet,trapcc,aml", help="learned backends (comma list)")
    parser.add_argument("--batches", default="32,256", help="batch sizes (comma list; default 32,256)")
    parser.add_argument("--points", type=int, default=512, help="points per input cloud (default 512)")
    parser.add_argument("--repeat", type=int, default=10, help="timed interleaved rounds (default 10)")
    parser.add_argument("--cpu-threads", type=int, default=1, help="intra-op threads of the CPU completer")


def _completers(name: str, batch: int) -> dict[str, Any]:
    from pcc_ros.models import load_completer

    return {
        "cpu": load_completer(name, device="cpu", batch_size=batch),
        "cuda_fp32": load_completer(name, device="cuda", batch_size=batch),
        "cuda_fp16": load_completer(name, device="cuda", batch_size=batch, half_precision=True),
    }


def _max_chamfer(a: list[np.ndarray], b: list[np.ndarray]) -> float:
    from pcc_ros.metrics.chamfer import chamfer_batch

    return float(chamfer_batch(b, a)["cd_l1"].max())


def run(args: argparse.Namespace) -> dict:
    import torch

    if not torch.cuda.is_available():
        reason = "no CUDA device on this machine: nothing to measure"
        print(reason)
        return {"skipped": reason}
    torch.set_num_threads(args.cpu_threads)
    batches = [int(b) for b in args.batches.split(",") if b.strip()]
    clouds = car_clouds(max(batches), args.points, args.seed)
    rows, results = [], {"device": torch.cuda.get_device_name(0), "torch": torch.__version__,
                         "inputs": f"car-like clouds, {args.points} points", "load_average_before": load_average()}
    for name in [n.strip() for n in args.backends.split(",") if n.strip()]:
        for batch in batches:
            completers = _completers(name, batch)
            inputs = clouds[:batch]
            context = frame_contexts(inputs) if getattr(completers["cpu"], "uses_context", False) else None
            outputs = {}
            for key, c in completers.items():
                torch.manual_seed(args.seed)  # AML samples its surface: one seed for every setting
                outputs[key] = c.complete(inputs, context)
            diffs = {k: _max_chamfer(outputs["cpu"], outputs[k]) for k in TOLERANCE}
            agree = {k: diffs[k] <= tol for k, tol in TOLERANCE.items()}
            calls = {k: (lambda c=c, x=inputs, ctx=context: c.complete(x, ctx)) for k, c in completers.items()}
            times = interleaved(calls, args.repeat)
            for key in completers:
                s = summary_ms(times[key])
                rows.append({"backend": name, "batch": batch, "setting": key, "min_ms": s["min_ms"],
                             "median_ms": s["median_ms"], "max_ms": s["max_ms"],
                             "inst_s": batch / (s["median_ms"] / 1e3),
                             "cd_l1_vs_cpu": diffs.get(key, 0.0),
                             "agrees": agree.get(key, True)})
    print_table(f"completion on {results['device']} vs the CPU ({args.cpu_threads} thread(s)); "
                f"median of {args.repeat} interleaved rounds, ms per batch", rows)
    for row in rows:
        if not row["agrees"]:
            print(f"{row['backend']} {row['setting']} batch {row['batch']}: output differs from the CPU's: Chamfer-L1 "
                  f"{row['cd_l1_vs_cpu']:.2e} (tolerance {TOLERANCE[row['setting']]})")
    results.update(rows=rows, load_average_after=load_average())
    return results
