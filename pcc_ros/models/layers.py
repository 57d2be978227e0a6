"""Shared torch building blocks for the completion backends.

Point clouds of real cars have very different sizes (a distant car has 30 points, a close
one 3000). Resampling every cloud to a fixed size wastes most of the compute on duplicates,
so the encoders here work on a *packed* batch: all points of all instances concatenated
into one ``(P, 3)`` tensor plus a ``(P,)`` segment id saying which instance (or which
instance-and-region) each point belongs to. Max-pooling is a segment-wise max (segments sorted), so
the cost is proportional to the real number of points.

The PCN-style encoder and the folding decoder below are algebraically the published
architectures; where a layer is applied to a concatenation ``[per-point ; per-segment]``
it is split into two linear maps (``W [a; b] = W_a a + W_b b``) so the per-segment half is
computed once per segment instead of once per point. That is the same function with the
same parameters count, only cheaper — it is what makes the folding decoder affordable on
a CPU.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from torch import nn

from pcc_ros.models.inference import Workspace, as_numpy, kernels_for
from pcc_ros.scratch import Scratch

#: Bytes of intermediates per chunk of the fused inference paths (one thread): a chunk's
#: features (every layer's output for its rows, float32) stay in a core's L2 cache (2 MiB here)
#: instead of ``(P, C)`` tensors that make a round trip through memory; a chunk's rows follow
#: from the widths (the global encoder ~1100 rows, the narrow local one ~2000, the folding
#: decoders 4096 / 9216 output points; measured with ``pcc bench complete``: narrower layers
#: gain from longer chunks, fewer operators per point).
CHUNK_BYTES = 5 << 19
#: With several intra-op threads every operator is a parallel region ending in a barrier,
#: and a barrier stalls whenever another process holds one of the cores: there, fewer and
#: larger operators win (measured with ``pcc bench complete``), so chunks grow by this factor.
MULTI_THREAD_CHUNK_FACTOR = 16
#: The compiled loops (:mod:`pcc_ros.models.kernels`) chunk with :data:`CHUNK_BYTES` divided by
#: this: they keep every layer's output of a chunk in its own work array (no buffer shared between
#: two layers as the operator path does), and half the operator path's budget measured about 1 %
#: faster on the whole network (``pcc bench complete``, 1 thread; a third: the same).
COMPILED_CHUNK_DIVISOR = 2



def _rows_for(widths: Sequence[int], compiled: bool = False) -> int:
    """Rows per chunk when each row has float32 intermediates of these ``widths``: the operator
    path's :data:`CHUNK_BYTES` (times :data:`MULTI_THREAD_CHUNK_FACTOR` with several intra-op
    threads), the ``compiled`` loops' that over :data:`COMPILED_CHUNK_DIVISOR` (their products
    run on one BLAS thread, whatever torch's count)."""
    if compiled:
        return max(1, CHUNK_BYTES // COMPILED_CHUNK_DIVISOR // (4 * max(1, sum(widths))))
    rows = max(1, CHUNK_BYTES // (4 * max(1, sum(widths))))
    return rows if torch.get_num_threads() == 1 else rows * MULTI_THREAD_CHUNK_FACTOR


def segment_max(
    features: torch.Tensor, segment: torch.Tensor, num_segments: int, method: str | None = None
) -> torch.Tensor:
    """Channel-wise max of ``features`` ``(P, C)`` per segment id ``(P,)`` -> ``(S, C)``.

    Empty segments come out as zeros; callers mask them. ``method``: ``"scatter"``
    (``scatter_reduce`` amax, the default) or ``"segment_reduce"`` (the original
    implementation, what the ``reference`` inference path runs; it needs ``segment`` sorted,
    which packing gives for free). Both return bit-identical values (a max is exact); the
    scatter is many times faster on CPU.
    """
    method = method or "scatter"
    if features.shape[0] == 0:
        return features.new_zeros(num_segments, features.shape[1])
    if method == "segment_reduce":
        lengths = torch.bincount(segment, minlength=num_segments)
        out = torch.segment_reduce(features, "max", lengths=lengths, unsafe=True)
        return torch.where((lengths > 0)[:, None], out, torch.zeros_like(out))
    if method != "scatter":
        raise ValueError(f"segment_max: unknown method {method!r}")
    index = segment[:, None].expand(-1, features.shape[1])
    out = features.new_zeros(num_segments, features.shape[1])
    return out.scatter_reduce(0, index, features, "amax", include_self=False)


def fast_inference(module: nn.Module) -> bool:
    """The fused chunked path applies: no autograd needed and ``module`` not on the reference path."""
    return module.inference_path != "reference" and not (
        torch.is_grad_enabled() and any(p.requires_grad for p in module.parameters()))


def _linears(mlp: SharedMLP | None) -> list[nn.Linear]:
    return [] if mlp is None else [m for m in mlp.net if isinstance(m, nn.Linear)]


_workspace = Workspace()  # the operator path's buffers (torch, per thread)
_SCRATCH = Scratch()  # the compiled kernels' work arrays (numpy, per thread)


def _derived(module: nn.Module, slot: str, deps: Sequence[torch.Tensor | None], make):
    """``make()`` (values derived from ``deps``, ``module``'s parameters), computed once and kept
    in ``module`` under ``slot`` until a parameter it depends on changes (its storage or its
    in-place version: optimizer steps and ``load_state_dict`` bump it; an edit through
    ``param.data`` does not, and would leave it stale)."""
    key = tuple((None, 0) if t is None else (t.data_ptr(), t._version) for t in deps)
    cached = module.__dict__.get(slot)
    if cached is not None and cached[0] == key:
        return cached[1]
    with torch.no_grad():
        value = make()
    module.__dict__[slot] = (key, value)
    return value


def _plan(linears: Sequence[nn.Linear], last_bias: bool = True) -> list[tuple[torch.Tensor, torch.Tensor | None]]:
    """``(weight.t(), bias)`` of each layer, made once per call instead of once per chunk;
    ``last_bias=False`` leaves the last layer's bias out (the caller adds it)."""
    plan = [(lin.weight.t(), lin.bias) for lin in linears]
    if plan and not last_bias:
        plan[-1] = (plan[-1][0], None)
    return plan


def _mlp_into(
    x: torch.Tensor,
    plan: Sequence[tuple[torch.Tensor, torch.Tensor | None]],
    scratch: Sequence[torch.Tensor],
    out: torch.Tensor,
    last_relu: bool,
) -> torch.Tensor:
    """``x`` through the layers of ``plan`` (:func:`_plan`; ReLU in place between them), every
    layer writing into a preallocated buffer: ``scratch[i]`` (rows >= ``x``'s) for the hidden
    layers, ``out`` for the last."""
    r = x.shape[0]
    for i, (wt, bias) in enumerate(plan):
        last = i == len(plan) - 1
        dest = out if last else scratch[i][:r]
        x = torch.mm(x, wt, out=dest) if bias is None else torch.addmm(bias, x, wt, out=dest)
        if not last or last_relu:
            x.relu_()
    return x


class SharedMLP(nn.Module):
    """Point-wise MLP (the 1x1 convolution of PointNet/PCN) over the last dimension.

    ReLU between layers; the last layer is linear unless ``final_relu``.
    """

    def __init__(self, in_dim: int, widths: Sequence[int], final_relu: bool = False) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        last = in_dim
        for i, w in enumerate(widths):
            layers.append(nn.Linear(last, w))
            if i < len(widths) - 1 or final_relu:
                layers.append(nn.ReLU(inplace=True))
            last = w
        self.net = nn.Sequential(*layers)
        self.out_dim = last

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)


class PCNEncoder(nn.Module):
    """PCN encoder on a packed batch.

    ``mlp1`` (3 -> widths1) per point, max-pool per segment, concatenate the pooled feature
    to every point of its segment, ``mlp2`` (2*widths1[-1] -> widths2) per point, max-pool.
    The first layer of ``mlp2`` is split into a point part and a segment part (see module doc).
    """

    def __init__(self, widths1: Sequence[int], widths2: Sequence[int]) -> None:
        super().__init__()
        if len(widths2) < 1:
            raise ValueError("widths2 needs at least one layer")
        self.mlp1 = SharedMLP(3, widths1)
        c1 = self.mlp1.out_dim
        self.point_proj = nn.Linear(c1, widths2[0])
        self.segment_proj = nn.Linear(c1, widths2[0], bias=False)
        self.mlp2 = SharedMLP(widths2[0], widths2[1:]) if len(widths2) > 1 else None
        self.out_dim = widths2[-1]
        self._single = len(widths2) == 1
        #: how inference runs (:mod:`pcc_ros.models.inference`; its completer sets it)
        self.inference_path = "auto"

    def forward(self, points: torch.Tensor, segment: torch.Tensor, num_segments: int) -> torch.Tensor:
        """``points`` ``(P, 3)``, ``segment`` ``(P,)`` in ``[0, num_segments)`` -> ``(S, out_dim)``."""
        if fast_inference(self):
            pooled = self._forward_compiled(points, segment, num_segments)
            return self._forward_chunked(points, segment, num_segments) if pooled is None else pooled
        method = "segment_reduce" if self.inference_path == "reference" else "scatter"
        f = self.mlp1(points)
        g = segment_max(f, segment, num_segments, method)
        h = self.point_proj(f) + self.segment_proj(g)[segment]
        if not self._single:
            h = self.mlp2(torch.relu(h))
        return segment_max(h, segment, num_segments, method)

    def _forward_chunked(self, points: torch.Tensor, segment: torch.Tensor, num_segments: int) -> torch.Tensor:
        """Inference: the same function, row chunk by row chunk, pooled as it goes.

        Every intermediate lives in a per-thread buffer reused by every chunk and every call
        (:class:`~pcc_ros.models.inference.Workspace`), so the matrix products write into memory already in the core's
        cache instead of a fresh allocation per product. With sorted segments (packed batches)
        a chunk holds whole segments, so both passes run on it while its ``mlp1`` features are
        still in cache, and where mlp1's last layer is narrower at its input than at its output
        it is composed with the split layer's point half (no ReLU between them:
        ``W_p (W_1 t + b_1) = (W_p W_1) t + W_p b_1``, fewer multiply-adds); otherwise the
        features of all points are kept for the second pass. Biases are folded where a max or
        a linear map lets them through (the same function; float rounding may differ in the
        last bits): ``mlp1``'s last bias goes after its max (exact: rounding is monotonic,
        ``max(a_i + b) == max(a_i) + b``) and into the split layer's once-per-segment half, with
        the point half's bias; the last layer's bias is added after the max.
        """
        p, s = points.shape[0], num_segments
        if p == 0:
            return points.new_zeros(s, self.out_dim)
        counts = torch.bincount(segment, minlength=s)
        nonempty = (counts > 0)[:, None]
        first, rest = _linears(self.mlp1), _linears(self.mlp2)
        rows = _rows_for([lin.out_features for lin in first] + [self.point_proj.out_features] +
                         [lin.out_features for lin in rest])
        aligned = bool((segment[1:] >= segment[:-1]).all())
        if aligned:
            chunks = _segment_chunks(counts, rows)
        else:
            chunks = [(a, min(a + rows, p), 0, s) for a in range(0, p, rows)]
        most = max(stop - start for start, stop, _, _ in chunks)
        ws = _workspace
        c1, hp = first[-1].out_features, self.point_proj.out_features
        w1 = first[-1].weight  # (c1, c0)
        composed = aligned and len(first) > 1 and w1.shape[1] < c1
        hidden = [ws.get(self, f"mlp1.{i}", most, lin.out_features, points) for i, lin in enumerate(first[:-1])]
        h = ws.get(self, "h", most, hp, points)
        inner = [ws.get(self, f"mlp2.{i}", most, lin.out_features, points) for i, lin in enumerate(rest[:-1])]
        if not composed:  # (the composed path writes mlp1's output and mlp2's last into one buffer)
            f = ws.get(self, "f", most if aligned else p, c1, points)
            inner += [ws.get(self, f"mlp2.{len(rest) - 1}", most, self.out_dim, points)] if rest else []
        gp = ws.get(self, "gp", s, hp, points)
        g = points.new_full((s, c1), -torch.inf)  # max of mlp1 without its last bias
        pool = points.new_full((s, self.out_dim), -torch.inf)
        first_plan, rest_plan = _plan(first, last_bias=False), _plan(rest, last_bias=False)
        wp, wseg = self.point_proj.weight.t(), self.segment_proj.weight.t()
        wc, const = self._folded(composed)
        idx = segment[:, None]  # the scatters' index, expanded to each width once per call
        idx_g, idx_pool = idx.expand(p, c1), idx.expand(p, self.out_dim)

        def first_pass(start: int, stop: int, dest: torch.Tensor) -> None:
            _mlp_into(points[start:stop], first_plan, hidden, dest, last_relu=False)
            g.scatter_reduce_(0, idx_g[start:stop], dest, "amax")

        def second_pass(start: int, stop: int, fc: torch.Tensor) -> None:
            hc = torch.index_select(gp, 0, segment[start:stop], out=h[: stop - start]).addmm_(fc, wp)  # in place
            if rest:
                hc.relu_()
                hc = _mlp_into(hc, rest_plan, inner[:-1], inner[-1][: stop - start], last_relu=False)
            pool.scatter_reduce_(0, idx_pool[start:stop], hc, "amax")

        if composed:
            # mlp1's last layer and the split layer's point half compose (no ReLU between them):
            # W_p f' = (W_p W1) t from mlp1's last hidden features t, c0 hp instead of c1 hp
            # multiply-adds per point (fewer whenever c0 < c1). f' is dead before the chunk's
            # last layer writes, so the two share one buffer (a smaller working set in cache).
            w1t = w1.t()
            out_buf = ws.get(self, "out", most, max(c1, self.out_dim), points).view(-1)
            hidden_plan, t_buf = first_plan[:-1], hidden[:-1]
            for start, stop, lo, hi in chunks:
                r = stop - start
                t = _mlp_into(points[start:stop], hidden_plan, t_buf, hidden[-1][:r], last_relu=True)
                fc = torch.mm(t, w1t, out=out_buf[: r * c1].view(r, c1))
                g.scatter_reduce_(0, idx_g[start:stop], fc, "amax")
                torch.addmm(const, g[lo:hi], wseg, out=gp[lo:hi])  # the chunk's segments are complete now
                hc = torch.index_select(gp, 0, segment[start:stop], out=h[:r]).addmm_(t, wc)
                if rest:
                    hc.relu_()
                    hc = _mlp_into(hc, rest_plan, inner, out_buf[: r * self.out_dim].view(r, self.out_dim),
                                   last_relu=False)
                pool.scatter_reduce_(0, idx_pool[start:stop], hc, "amax")
        elif aligned:
            for start, stop, lo, hi in chunks:
                fc = f[: stop - start]
                first_pass(start, stop, fc)
                torch.addmm(const, g[lo:hi], wseg, out=gp[lo:hi])  # the chunk's segments are complete now
                second_pass(start, stop, fc)
        else:
            for start, stop, _, _ in chunks:
                first_pass(start, stop, f[start:stop])
            torch.addmm(const, torch.where(nonempty, g, 0.0), wseg, out=gp)
            for start, stop, _, _ in chunks:
                second_pass(start, stop, f[start:stop])
        if rest and rest[-1].bias is not None:
            pool += rest[-1].bias
        return pool.masked_fill_(~nonempty, 0.0)

    def _forward_compiled(self, points: torch.Tensor, segment: torch.Tensor, num_segments: int) -> torch.Tensor | None:
        """:meth:`_forward_chunked`'s composed path in one compiled call
        (:func:`pcc_ros.models.kernels.encode`: the same products and folded constants, the
        chunks, the pooling, the last bias and the empty segments in the kernel, no torch
        operator between them); None where it does not apply (not a compiled path, GPU, not
        float32, other than two ``mlp1`` layers composed with one ``mlp2`` layer, segments not
        sorted), and :meth:`_forward_chunked` runs instead."""
        kernels = kernels_for(self.inference_path, points)
        weights = self.kernel_weights() if kernels is not None and len(points) else None
        if weights is None:
            return None
        counts = kernels.sorted_counts(segment.numpy(), num_segments)
        if len(counts) != num_segments:
            return None
        pool = np.empty((num_segments, self.out_dim), np.float32)
        work = kernels.work_memory(_SCRATCH, "encoder", kernels.encoder_floats(weights, counts))
        kernels.encode(weights, as_numpy(points), counts, pool, work, kernels.blas_routes.route())
        return torch.from_numpy(pool)

    def kernel_weights(self):
        """This encoder for the compiled loops: :class:`pcc_ros.models.kernels.EncoderWeights`
        (derived from the parameters, kept while they are unchanged: :func:`_derived`), or None
        where its structure is not the one the kernel runs (two ``mlp1`` layers composed with
        one ``mlp2`` layer, biases)."""
        first, rest = _linears(self.mlp1), _linears(self.mlp2)
        if len(first) != 2 or len(rest) != 1 or first[1].in_features >= first[1].out_features or first[0].bias is None:
            return None
        last = rest[0]

        def make():
            from pcc_ros.models.kernels import EncoderWeights

            wc, const = self._folded(True)
            rows = _rows_for([first[0].out_features, first[1].out_features, self.point_proj.out_features,
                              self.out_dim], compiled=True)
            return EncoderWeights(*(as_numpy(t) for t in (
                first[0].weight.t(), first[0].bias, first[1].weight.t(), wc, self.segment_proj.weight.t(), const,
                last.weight.t(), last.bias if last.bias is not None else torch.zeros(self.out_dim))), rows)

        return _derived(self, "_kernel_weights", tuple(self.parameters()), make)

    def _folded(self, composed: bool) -> tuple[torch.Tensor | None, torch.Tensor]:
        """The folded constants of :meth:`_forward_chunked`: ``(W_p W1)^T`` (``composed``; else
        None) and the per-segment half's constant ``b_p + (W_p + W_s) b1``, kept while the
        parameters they come from are unchanged (:func:`_derived`)."""
        last = _linears(self.mlp1)[-1]

        def make():
            wc = (self.point_proj.weight @ last.weight).t() if composed else None  # a transposed weight
            b1 = last.bias
            const = self.point_proj.bias.clone() if b1 is None else torch.addmv(
                self.point_proj.bias, self.point_proj.weight + self.segment_proj.weight, b1)
            return wc, const

        deps = (self.point_proj.weight, self.point_proj.bias, self.segment_proj.weight, last.weight, last.bias)
        return _derived(self, f"_folded_{composed}", deps, make)


def _segment_chunks(counts: torch.Tensor, rows: int) -> list[tuple[int, int, int, int]]:
    """Chunks of whole segments (sorted ids with these ``counts``), each at most ``rows`` rows
    unless one segment alone is longer (then that segment is its chunk), as
    ``(first row, stop row, first segment, stop segment)``."""
    cum = np.cumsum(counts.cpu().numpy())  # the counts may live on the GPU
    ends = cum[np.r_[True, cum[1:] != cum[:-1]] & (cum > 0)]  # one end per nonempty segment
    starts, stops, start = [], [], 0
    while start < ends[-1]:
        j = int(np.searchsorted(ends, start + rows, side="right"))
        stop = int(ends[j - 1]) if j > 0 and ends[j - 1] > start else int(ends[np.searchsorted(ends, start, "right")])
        starts.append(start)
        stops.append(stop)
        start = stop
    first = np.searchsorted(cum, starts, side="right")  # the segment of each chunk's first row
    last = np.searchsorted(cum, np.asarray(stops) - 1, side="right")  # ... and of its last row
    return list(zip(starts, stops, first.tolist(), (last + 1).tolist(), strict=True))


def set_decode_density(model: nn.Module, density: int) -> int:
    """:meth:`FoldingDecoder.set_density` on every folding decoder of ``model``; returns how many."""
    decoders = [m for m in model.modules() if isinstance(m, FoldingDecoder)]
    for decoder in decoders:
        decoder.set_density(density)
    return len(decoders)


def folding_grid(size: int, scale: float) -> torch.Tensor:
    """``(size*size, 2)`` regular 2-D grid in ``[-scale, scale]^2`` (a single point at 0 for size 1)."""
    if size == 1:
        return torch.zeros(1, 2)
    t = torch.linspace(-scale, scale, size)
    gx, gy = torch.meshgrid(t, t, indexing="ij")
    return torch.stack([gx.reshape(-1), gy.reshape(-1)], dim=1)


def _fits(out: torch.Tensor, codes: int, points: int) -> bool:
    """``out`` can hold ``codes`` decoded clouds of ``points`` points as ``(codes / m, m * points, 3)``."""
    rows = out.shape[0] if out.dim() == 3 else -1
    if rows <= 0 or out.shape[2] != 3:
        return rows == 0 and codes == 0
    return codes % rows == 0 and out.shape[1] == codes // rows * points


class FoldingDecoder(nn.Module):
    """PCN decoder: fully connected layers to ``num_coarse`` points, then one folding step.

    Each coarse point is expanded into ``grid_size**2`` points by an MLP over
    ``[grid coordinate ; coarse point ; code]``, whose output is added to the coarse point
    (residual). The first folding layer is split so the code part is computed once per
    segment (the reason the published decoder over 1029-wide features is affordable here).
    Output: ``num_coarse * grid_size**2`` points.
    """

    def __init__(
        self,
        code_dim: int,
        fc_widths: Sequence[int],
        num_coarse: int,
        grid_size: int,
        fold_widths: Sequence[int],
        grid_scale: float,
    ) -> None:
        super().__init__()
        if len(fold_widths) < 1:
            raise ValueError("fold_widths needs at least one hidden layer")
        self.num_coarse = num_coarse
        self.grid_size, self.grid_scale = int(grid_size), float(grid_scale)
        self.fc = SharedMLP(code_dim, [*fc_widths, num_coarse * 3])
        self.register_buffer("grid", folding_grid(grid_size, grid_scale), persistent=False)
        h = fold_widths[0]
        self.fold_code = nn.Linear(code_dim, h)
        self.fold_point = nn.Linear(3, h, bias=False)
        self.fold_grid = nn.Linear(2, h, bias=False)
        self.fold_mlp = SharedMLP(h, [*fold_widths[1:], 3])
        self.num_points = num_coarse * self.grid.shape[0]
        #: how inference runs (:mod:`pcc_ros.models.inference`; its completer sets it)
        self.inference_path = "auto"

    def set_density(self, density: int) -> None:
        """Decode ``density`` times finer along each grid axis (inference): the grid side becomes
        ``(grid_size - 1) * density + 1`` over the same span, so the trained grid points stay and
        the new ones lie between them on each coarse point's folded patch. ``1``: as trained."""
        density = int(density)
        if density < 1:
            raise ValueError(f"decode density must be >= 1, got {density}")
        size = self.grid_size if self.grid_size == 1 else (self.grid_size - 1) * density + 1
        self.grid = folding_grid(size, self.grid_scale).to(self.grid.device, self.grid.dtype)
        self.num_points = self.num_coarse * self.grid.shape[0]

    def forward(self, code: torch.Tensor, out: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """``code`` ``(S, code_dim)`` -> ``(coarse (S, K, 3), fine (S, K*G, 3))``.

        ``out``: where ``fine`` is written, ``(S / m, m * K * G, 3)`` for a divisor ``m`` of ``S``
        (``m`` consecutive codes per row: PointPnCNet's eight octants of a car), possibly a strided
        view of a bigger tensor (the completer's output); ``fine`` is then ``out`` itself.
        """
        s = code.shape[0]
        coarse = self.fc(code).view(s, self.num_coarse, 3)
        if out is not None and not _fits(out, s, self.num_points):
            raise ValueError(f"FoldingDecoder: out of shape {tuple(out.shape)} for {s} codes of "
                             f"{self.num_points} points")
        if fast_inference(self):
            return coarse, self._fold_chunked(code, coarse, out)
        h = (
            self.fold_code(code)[:, None, None, :]
            + self.fold_point(coarse)[:, :, None, :]
            + self.fold_grid(self.grid)[None, None, :, :]
        )
        offset = self.fold_mlp(torch.relu(h))
        fine = (coarse[:, :, None, :] + offset).reshape(s, -1, 3)
        if out is None:
            return coarse, fine
        return coarse, out.copy_(fine.view(out.shape))

    def _fold_chunked(self, code: torch.Tensor, coarse: torch.Tensor, out: torch.Tensor | None) -> torch.Tensor:
        """Inference: the folding step a few instances at a time, intermediates in per-thread
        buffers (:class:`~pcc_ros.models.inference.Workspace`). The last layer (a few output columns, where a product
        ``rows x C @ C x 3`` runs far below the matmul rate) is computed transposed, ``W h^T``
        ``(3, rows)``, and the residual sum ``fine = (coarse + b) + h W^T`` is one broadcast add
        from it and the coarse points straight into the output (the same function; float
        rounding may differ in the last bits)."""
        s, k = coarse.shape[:2]
        g = self.grid.shape[0]
        hdim = self.fold_point.out_features
        layers = _linears(self.fold_mlp)
        if out is None:
            out = torch.empty(s, k * g, 3, dtype=coarse.dtype, device=coarse.device)
        m = s // out.shape[0] if out.shape[0] else 1  # codes per row of out
        kernels = kernels_for(self.inference_path, code)
        if kernels is not None and self._fold_weights() is None:  # not the folding MLP they run
            kernels = None
        step = self.fold_step(m, compiled=kernels is not None)
        if kernels is not None:  # the same steps as the loop below, compiled
            return self._fold_compiled(kernels, code, coarse, out, m, step)
        ws = _workspace
        grid = self.fold_grid(self.grid)  # (G, H)
        plan, last = _plan(layers[:-1]), layers[-1]
        start_points = (coarse if last.bias is None else coarse + last.bias)[:, :, None, :]  # (S, K, 1, 3)
        most = min(step, s) * k * g
        h = ws.get(self, "h", most, hdim, code)
        hidden = [ws.get(self, f"fold.{i}", most, lin.out_features, code) for i, lin in enumerate(layers[:-1])]
        base = ws.get(self, "base", s * k, hdim, code)
        torch.mm(coarse.reshape(s * k, 3), self.fold_point.weight.t(), out=base)
        base = base.view(s, k, hdim).add_(self.fold_code(code)[:, None, :])  # (S, K, H)
        for start in range(0, s, step):
            stop = min(start + step, s)
            n, r = stop - start, (stop - start) * k * g
            hc = h[:r]
            torch.add(base[start:stop, :, None, :], grid, out=hc.view(n, k, g, hdim)).relu_()
            x = _mlp_into(hc, plan, hidden, hidden[-1][:r], last_relu=True) if plan else hc
            yt = torch.mm(last.weight, x.t(), out=ws.get(self, "yt", 3, r, code))  # (3, r)
            dest = out[start // m : stop // m].view(n // m, m, k, g, 3)
            torch.add(start_points[start:stop].view(n // m, m, k, 1, 3), yt.t().view(n // m, m, k, g, 3), out=dest)
        return out

    def fold_step(self, m: int, compiled: bool) -> int:
        """Codes per chunk of the folding step (a multiple of ``m``, the codes per output row):
        as many as :func:`_rows_for` allows for the ``compiled`` loops or the operators."""
        widths = [self.fold_point.out_features, *(lin.out_features for lin in _linears(self.fold_mlp))]
        return max(1, _rows_for(widths, compiled=compiled) // (self.num_points * m)) * m

    def _fold_weights(self):
        """The folding step for :func:`pcc_ros.models.kernels.fold`:
        :class:`pcc_ros.models.kernels.FoldWeights` (kept while the parameters and the grid are
        unchanged: :func:`_derived`), or None where the folding MLP is not the one it runs (one
        hidden layer with a bias, 3 outputs)."""
        layers = _linears(self.fold_mlp)
        if len(layers) != 2 or layers[1].out_features != 3 or layers[0].bias is None:
            return None
        hidden, last = layers

        def make():
            from pcc_ros.models.kernels import FoldWeights

            return FoldWeights(*(as_numpy(t) for t in (
                self.fold_grid(self.grid), self.fold_point.weight.t(), hidden.weight.t(), hidden.bias, last.weight,
                last.bias if last.bias is not None else torch.zeros(3))))

        deps = (self.grid, self.fold_grid.weight, self.fold_point.weight, *hidden.parameters(), *last.parameters())
        return _derived(self, "_kernel_weights", deps, make)

    def kernel_weights(self, codes_per_row: int):
        """The whole decoder for :func:`pcc_ros.models.kernels.pointpncnet_infer`:
        :class:`pcc_ros.models.kernels.DecoderWeights` (the fully connected layers, the code
        projection, :meth:`_fold_weights`; its chunks for ``codes_per_row`` codes per output
        row), or None where the folding MLP is not the compiled one."""
        from pcc_ros.models.kernels import DecoderWeights

        fold = self._fold_weights()
        if fold is None:
            return None
        return DecoderWeights(dense_weights(self.fc), dense_weights(self.fold_code), fold, self.num_coarse,
                              self.fold_step(codes_per_row, compiled=True))

    def _fold_compiled(self, kernels, code: torch.Tensor, coarse: torch.Tensor, out: torch.Tensor, m: int,
                       step: int) -> torch.Tensor:
        """:meth:`_fold_chunked` (one hidden folding layer) in one compiled call
        (:func:`pcc_ros.models.kernels.fold_into`): the same function, the first layer's point and grid
        halves and the output layer's residual inside the kernel."""
        weights = self._fold_weights()
        need = kernels.fold_floats(weights, coarse.shape[0], coarse.shape[1], step)
        work = kernels.work_memory(_SCRATCH, "fold", need)
        kernels.fold_into(as_numpy(coarse), as_numpy(self.fold_code(code)), weights, out.numpy(), m, step, work,
                          kernels.blas_routes.route())
        return out


def dense_weights(module: nn.Module):
    """``module``'s fully connected layers (a :class:`SharedMLP` without a final ReLU, or one
    ``nn.Linear``) for :func:`pcc_ros.models.kernels.dense`:
    :class:`pcc_ros.models.kernels.DenseWeights`, kept while the parameters are unchanged
    (:func:`_derived`)."""
    linears = [module] if isinstance(module, nn.Linear) else _linears(module)
    if isinstance(module, SharedMLP) and isinstance(module.net[-1], nn.ReLU):
        raise ValueError("dense_weights: the compiled layers end without a ReLU")

    def make():
        from pcc_ros.models.kernels import DenseWeights

        zeros = [torch.zeros(lin.out_features) if lin.bias is None else lin.bias for lin in linears]
        return DenseWeights(as_numpy(torch.cat([lin.weight.t().reshape(-1) for lin in linears])),
                            as_numpy(torch.cat(zeros)),
                            np.array([linears[0].in_features, *(lin.out_features for lin in linears)], np.int64))

    return _derived(module, "_dense_weights", tuple(module.parameters()), make)
