"""Section 5 of ``pcc bench complete`` (where the time goes): the network's matrix products
recorded and replayed alone, the time per part of the network, and the operator profile of the
torch-operator path (the module doc of :mod:`benchmarks.complete` says what each measures)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from benchmarks.common import inference_path, interleaved, print_table
from benchmarks.complete import ceiling_calls, ceiling_rates, linear_flops_by


def recorded_matmuls(call: Callable[[], object]) -> list[tuple[int, int, int]]:
    """``(M, K, N)`` of every ``mm`` / ``addmm`` / ``addmm_`` that ``call()`` runs, in order."""
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CPU], record_shapes=True) as prof:
        call()
    shapes = []
    for event in prof.events():
        dims = [list(d) for d in event.input_shapes if isinstance(d, list | tuple)]
        if event.name == "aten::mm" and len(dims) >= 2:
            (m, k), (_, n) = dims[0], dims[1]
        elif event.name in ("aten::addmm", "aten::addmm_") and len(dims) >= 3:
            (m, k), (_, n) = dims[1], dims[2]
        else:
            continue
        shapes.append((int(m), int(k), int(n)))
    return shapes


def matmul_replay(shapes: list[tuple[int, int, int]], weight_layout: bool = True) -> Callable[[], None]:
    """A callable running ``torch.mm`` at each shape in order; with ``weight_layout`` the right
    operand is a transposed ``(N, K)`` matrix, as the network's ``weight.t()`` (MKL's speed at
    few output columns depends on it several-fold). One set of operands per layer shape
    ``K x N``, its rows sliced by every call of that shape, as the network slices its reused
    buffers: the replay's operands stay in cache, so its rate bounds what these shapes allow."""
    import torch

    def right(k: int, n: int):
        return torch.randn(n, k).t() if weight_layout else torch.randn(k, n)

    rows: dict[tuple[int, int], int] = {}
    for m, k, n in shapes:
        rows[k, n] = max(m, rows.get((k, n), 0))
    sets = {(k, n): (torch.randn(m, k), right(k, n), torch.empty(m, n)) for (k, n), m in rows.items()}
    operands = [(sets[k, n][0][:m], sets[k, n][1], sets[k, n][2][:m]) for m, k, n in shapes]

    def replay() -> None:
        for a, b, out in operands:
            torch.mm(a, b, out=out)

    return replay


def part_times(completer, batch: list, repeat: int) -> list[dict[str, Any]]:
    """Wall time of each encoder and folding decoder of the network per batch (fast path,
    forward hooks, median of ``repeat`` calls) and its share of the nominal FLOPs."""
    import time

    from pcc_ros.models.layers import FoldingDecoder, PCNEncoder

    parts = [(n, m) for n, m in completer.model.named_children() if isinstance(m, PCNEncoder | FoldingDecoder)]
    flops = linear_flops_by(completer, dict(parts), lambda: completer.complete(batch))
    spent: dict[str, list[float]] = {n: [] for n, _ in parts}
    start: dict[str, float] = {}
    handles = []
    for name, part in parts:
        handles.append(part.register_forward_pre_hook(
            lambda mod, inputs, name=name: start.__setitem__(name, time.perf_counter())))
        handles.append(part.register_forward_hook(
            lambda mod, inputs, output, name=name: spent[name].append(time.perf_counter() - start[name])))
    total, per_call = [], {name: [] for name, _ in parts}
    try:
        completer.complete(batch)
        for _ in range(repeat):
            for name in spent:
                spent[name].clear()
            tic = time.perf_counter()
            completer.complete(batch)
            total.append(time.perf_counter() - tic)
            for name in spent:  # a part may run once per chunk of the batch
                per_call[name].append(sum(spent[name]))
    finally:
        for h in handles:
            h.remove()
    # every part's share of each call, then the median share (robust to load that hits one call)
    total_s = np.asarray(total)
    shares = {name: np.asarray(per_call[name]) / total_s for name, _ in parts}
    shares["rest (packing, attention, outputs)"] = 1.0 - sum(shares.values())
    all_flops = sum(flops.values())
    return [{"part": name, "ms": float(np.median(share * total_s)) * 1e3, "time_share": float(np.median(share)),
             "nominal_flop_share": flops.get(name, 0) / all_flops} for name, share in shares.items()]


#: How :func:`op_profile` groups the network's operators.
OP_GROUPS = {
    "matrix products": ("aten::mm", "aten::addmm", "aten::addmm_", "aten::linear", "aten::matmul", "aten::addmv"),
    "max-pooling scatters": ("aten::scatter_reduce_", "aten::scatter_reduce", "aten::segment_reduce"),
    "gathers": ("aten::index_select", "aten::index"),
    "elementwise passes and copies": ("aten::add", "aten::add_", "aten::relu_", "aten::relu", "aten::clamp_min_",
                                      "aten::mul", "aten::where", "aten::masked_fill_", "aten::masked_fill",
                                      "aten::cat", "aten::copy_", "aten::softmax", "aten::sum", "aten::maximum"),
}


def op_profile(call: Callable[[], object], repeat: int) -> dict[str, Any]:
    """Every top-level ``aten`` operator ``call()`` runs (``torch.profiler``, ``repeat`` calls):
    ms per call (with its children: an ``addmm``'s bias copy counts as the product), calls per
    call and share of the profiled operator time; by operator and by :data:`OP_GROUPS`."""
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CPU]) as prof:
        for _ in range(repeat):
            call()
    spent: dict[str, float] = {}
    calls: dict[str, int] = {}
    for event in prof.events():
        if event.cpu_parent is None and event.name.startswith("aten::"):
            spent[event.name] = spent.get(event.name, 0.0) + event.cpu_time_total / 1e3 / repeat
            calls[event.name] = calls.get(event.name, 0) + 1
    total = sum(spent.values()) or 1.0
    group_of = {op: group for group, ops in OP_GROUPS.items() for op in ops}
    groups: dict[str, dict[str, float]] = {}
    for op, ms in spent.items():
        row = groups.setdefault(group_of.get(op, "rest (views, allocations, bookkeeping)"), {"ms": 0.0, "calls": 0})
        row["ms"] += ms
        row["calls"] += calls[op] // repeat
    ops = [{"op": op, "ms": ms, "calls": calls[op] // repeat, "share": ms / total,
            "group": group_of.get(op, "rest (views, allocations, bookkeeping)")}
           for op, ms in sorted(spent.items(), key=lambda kv: -kv[1])]
    by_group = [{"group": g, "ms": r["ms"], "calls": r["calls"], "share": r["ms"] / total}
                for g, r in sorted(groups.items(), key=lambda kv: -kv[1]["ms"])]
    return {"groups": by_group, "ops": ops, "profiled_ms": total}


def time_breakdown(completer, batch: list, repeat: int, flops_per_batch: float) -> dict[str, Any]:
    """Section 5: the network against a replay of its own matrix products, one thread."""
    import torch

    torch.set_num_threads(1)
    with inference_path(completer, "operators"):  # the same products as torch operators: the profiler records them
        shapes = recorded_matmuls(lambda: completer.complete(batch))
    replay = matmul_replay(shapes)
    alts: dict[str, Callable[[], object]] = {"network": lambda: completer.complete(batch), "matmul_replay": replay}
    ceiling_set = ceiling_calls()  # as in section 2: the fastest of the two shapes, fresh or reused output
    alts.update({name: call for name, (call, _) in ceiling_set.items()})
    times = interleaved(alts, repeat)
    network, replayed = float(np.median(times["network"])), float(np.median(times["matmul_replay"]))
    rates, fastest = ceiling_rates(ceiling_set, times)
    ceiling, ceiling_min = max(rates.values()), max(fastest.values())
    replay_flops = sum(2 * m * k * n for m, k, n in shapes)
    # per layer shape (in x out; the rows of a chunk vary): its share of the replayed FLOPs and its
    # own rate (timed alone, same rounds)
    groups: dict[tuple[int, int], list[int]] = {}
    for m, k, n in shapes:
        groups.setdefault((k, n), []).append(m)
    per_shape_alts = {f"{k}x{n}": matmul_replay([(m, k, n) for m in ms]) for (k, n), ms in groups.items()}
    shape_times = interleaved(per_shape_alts, max(5, repeat // 2))
    rows = []
    for (k, n), ms in sorted(groups.items(), key=lambda kv: -sum(kv[1]) * kv[0][0] * kv[0][1]):
        t = float(np.median(shape_times[f"{k}x{n}"]))
        flop = 2 * sum(ms) * k * n
        gflops = flop / t / 1e9
        rows.append({"k_x_n": f"{k}x{n}", "calls": len(ms), "rows_per_call": sum(ms) / len(ms),
                     "flop_share": flop / replay_flops, "ms": t * 1e3, "gflop_s": gflops,
                     "of_ceiling": gflops / ceiling})
    print_table("where the time goes (1 thread, batch 32): the network's matrix products replayed alone, "
                "by layer shape (in x out; the decoders' transposed 3-wide last layers: in x rows)",
                rows)
    out = {
        "network_ms": network * 1e3, "matmul_replay_ms": replayed * 1e3, "ceiling_gflop_s": ceiling,
        "network_gflop_s": flops_per_batch / network / 1e9,
        "replay_gflop_s": replay_flops / replayed / 1e9, "replay_flops": replay_flops,
        "outside_matmul_share": 1.0 - replayed / network, "shapes": rows,
    }
    out["network_of_ceiling"] = out["network_gflop_s"] / ceiling
    out["replay_of_ceiling"] = out["replay_gflop_s"] / ceiling
    # the least-disturbed rounds of each (see section 1)
    out["network_of_ceiling_min"] = flops_per_batch / float(np.min(times["network"])) / 1e9 / ceiling_min
    out["replay_of_ceiling_min"] = replay_flops / float(np.min(times["matmul_replay"])) / 1e9 / ceiling_min
    out["outside_matmul_share_min"] = 1.0 - float(np.min(times["matmul_replay"])) / float(np.min(times["network"]))
    with inference_path(completer, "compiled_layers"):  # one compiled call has no parts to hook
        out["parts"] = part_times(completer, batch, repeat)
    print_table("time per part of the network (1 thread, batch 32, fast path with the layers called one by one; "
                "FLOP share of the nominal count)", out["parts"])
    with inference_path(completer, "operators"):  # the compiled loops are one opaque call to the profiler
        out["operators"] = op_profile(lambda: completer.complete(batch), repeat)
    print_table(f"the fast path's operators with the compiled loops off, by kind (torch.profiler, {repeat} batches; "
                "ms per batch with the profiler's overhead, share of the profiled operator time)",
                out["operators"]["groups"])
    print_table("its 12 costliest operators", out["operators"]["ops"][:12], ["op", "group", "ms", "calls", "share"])
    print(f"network {out['network_ms']:.1f} ms per batch = {out['network_gflop_s']:.1f} GFLOP/s "
          f"({out['network_of_ceiling']:.0%} of the ceiling {ceiling:.1f} GFLOP/s); its matrix products replayed "
          f"alone: {out['matmul_replay_ms']:.1f} ms = {out['replay_gflop_s']:.1f} GFLOP/s "
          f"({out['replay_of_ceiling']:.0%} of the ceiling: the most these shapes allow); time outside matrix "
          f"products: {out['outside_matmul_share']:.0%} of the network's. Least-disturbed rounds: network "
          f"{out['network_of_ceiling_min']:.0%}, replay {out['replay_of_ceiling_min']:.0%} of the ceiling "
          f"{ceiling_min:.1f} GFLOP/s, outside {out['outside_matmul_share_min']:.0%}.")
    return out
