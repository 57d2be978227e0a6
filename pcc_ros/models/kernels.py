"""Compiled CPU inference loops of the PCN encoder and the folding decoder (numba).

Why: in eager PyTorch every step of a chunk is an operator call (5-10 us of dispatch) and a
pass through memory: the max-pooling scatters, the ReLUs, the folding decoder's broadcast adds
and its 3-wide output layer (a matrix product at a fifth of the matmul rate) took a fifth of
the network's time (``pcc bench complete``). Here a chunk's matrix products are calls into a
BLAS from inside the compiled code (:func:`pcc_ros.models.blas.gemm`: MKL's public
``cblas_sgemm`` where the ``mkl`` wheel is installed, else ``np.dot``, which numba hands to
SciPy's BLAS; every kernel takes the route as its ``blas`` argument, :func:`pcc_ros.models.blas.route`),
and the work between them is fused loops over
the chunk's rows while they are in cache (bias, ReLU, max-pooling, broadcast add, the 3-wide
output layer with its residual), with no Python between them.

The network is defined once, by the torch modules (``layers.PCNEncoder``,
``layers.FoldingDecoder``, ``pointpncnet_network.PointPnCNetNet``): each derives the weights its
kernel reads as one of the named structures below (``kernel_weights()``), the same parameters
with the same folded constants as the modules' chunked operator path; float rounding differs
in the last bits (``pcc bench complete`` and the tests compare the paths).

:func:`pointpncnet_infer` runs PointPnCNet's whole network in one call (both encoders, the
octant gather, the attention and fusion, both decoders' fully connected layers and folding):
called layer by layer, the Python and torch operators between the kernels, run while the
caches are cold from the kernel before, cost 4-5 % of the network's time (``pcc bench
complete``, the ``compiled_layers`` path).

Used on CPU float32 inference by a completer whose inference path allows it
(:mod:`pcc_ros.models.inference`); compiled on first use and cached on disk
(:func:`pcc_ros.jit.compiled`; :func:`warm_up` at model load).

BLAS threads: the kernels are called from each worker thread with one BLAS thread each
(parallelism comes from the completer's ``workers``): MKL runs on its sequential layer
(:mod:`pcc_ros.models.blas`), and ``import pcc_ros`` sets ``OPENBLAS_NUM_THREADS=1`` unless the
user set a count (why: :mod:`pcc_ros`).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit

from pcc_ros.jit import compiled
from pcc_ros.models import blas as blas_routes
from pcc_ros.models.blas import gemm

#: Kernels here compile :func:`gemm`'s overloads from this file too (:data:`pcc_ros.jit.CACHE_DEPENDS`).
CACHE_DEPENDS = ("blas.py",)


def _load_blas() -> bool:
    """Load SciPy's BLAS (what numba's ``np.dot`` calls); False where SciPy or its BLAS is
    missing: the completers then run the torch-operator path."""
    try:
        import scipy.linalg.cython_blas  # noqa: F401
    except ImportError:
        return False
    return True


#: Whether the compiled kernels can run here (numba, which imported this module, and SciPy's BLAS).
AVAILABLE = _load_blas()

#: Floats a work array's carved views start on a multiple of (a cache line: misaligned operands
#: slow the products); :func:`work_memory` hands out a work array that starts on one.
ALIGN = 16
#: The octants of PointPnCNet's local stream.
REGIONS = 8


class EncoderWeights(NamedTuple):
    """A PCN encoder for :func:`pcn_encode`: two ``mlp1`` layers, the second composed with the
    split layer's point half, one ``mlp2`` layer (``layers.PCNEncoder.kernel_weights``).
    Matrices are transposed, ``(in, out)``, float32."""

    layer0_t: np.ndarray  #: (3, c0) mlp1's first layer
    layer0_bias: np.ndarray  #: (c0,)
    layer1_t: np.ndarray  #: (c0, c1) mlp1's second layer, its bias folded into segment_const
    point_half_t: np.ndarray  #: (c0, h) the split layer's point half composed with layer 1
    segment_half_t: np.ndarray  #: (c1, h) the split layer's per-segment half
    segment_const: np.ndarray  #: (h,) the split layer's bias plus layer 1's bias through both halves
    last_t: np.ndarray  #: (h, out) mlp2's layer
    last_bias: np.ndarray  #: (out,)
    chunk_rows: int  #: rows per chunk of whole segments (one longer segment alone)


class DenseWeights(NamedTuple):
    """Fully connected layers for :func:`dense`, ReLU between them (``layers.dense_weights``)."""

    weights_t: np.ndarray  #: every layer's transposed (in, out) weight, flat, one after the other
    biases: np.ndarray  #: every layer's bias, flat, one after the other
    widths: np.ndarray  #: (layers + 1,) int64: the input width, then each layer's output width


class FoldWeights(NamedTuple):
    """The folding step for :func:`fold`: one hidden layer (``layers.FoldingDecoder``)."""

    grid_proj: np.ndarray  #: (G, h) the grid points through the first layer's grid half
    point_t: np.ndarray  #: (3, h) the first layer's coarse-point half
    hidden_t: np.ndarray  #: (h, h1) the hidden layer
    hidden_bias: np.ndarray  #: (h1,)
    out_weight: np.ndarray  #: (3, h1) the output layer, not transposed (three dot products a row)
    out_bias: np.ndarray  #: (3,)


class DecoderWeights(NamedTuple):
    """A folding decoder for :func:`decode` (``layers.FoldingDecoder.kernel_weights``)."""

    coarse: DenseWeights  #: the fully connected layers from the code to the coarse points
    code_proj: DenseWeights  #: the first folding layer's code half (one layer)
    fold: FoldWeights
    coarse_points: int  #: K: coarse points per code
    codes_per_chunk: int  #: codes folded per chunk (a multiple of the codes per output row)


class NetworkWeights(NamedTuple):
    """PointPnCNet's network for :func:`pointpncnet_infer`
    (``pointpncnet_network.PointPnCNetNet.kernel_weights``)."""

    global_encoder: EncoderWeights
    local_encoder: EncoderWeights
    attention: DenseWeights  #: embedding -> hidden -> 1 logit per octant
    global_decoder: DecoderWeights  #: one code per row of the output
    local_decoder: DecoderWeights  #: eight codes (the octants) per row of the output
    min_region_points: int  #: an octant with fewer input points is absent


def work_memory(scratch, name: str, floats: int) -> np.ndarray:
    """``floats`` float32 of ``scratch``'s ``name`` buffer (kept per thread from call to call:
    fresh memory costs page faults on every call, and its release stalls the other threads of
    the process), starting on a multiple of :data:`ALIGN` floats."""
    buf = scratch(name, floats + ALIGN, np.float32)
    skip = (-(buf.__array_interface__["data"][0] // 4)) % ALIGN
    return buf[skip: skip + floats]


@njit(inline="always")
def _carve(work, offset, rows, cols):
    """A ``(rows, cols)`` view of ``work`` from ``offset`` rounded up to a multiple of
    :data:`ALIGN` (``work`` starts on one: :func:`work_memory`), and the offset after it."""
    offset = (offset + ALIGN - 1) // ALIGN * ALIGN
    return work[offset: offset + rows * cols].reshape((rows, cols)), offset + rows * cols


@compiled()
def pcn_encode(points, counts, weights, out, layer0, layer1, hidden, last, pooled1, segment_half, blas):
    """The PCN encoder's composed inference path (points sorted by segment, ``counts`` per
    segment) on chunks of whole segments of about ``weights.chunk_rows`` rows:
    ``t = relu(p W0^T + b0)``, ``g = max_seg(t W1^T)``, ``h = relu(t Wc + (g Ws + const)[seg])``,
    ``out = max_seg(h W2^T) + b2`` (0 for an empty segment). ``layer0, layer1, hidden, last``:
    work arrays of ``max(chunk rows, largest segment)`` rows; ``pooled1, segment_half``: of a
    row per segment."""
    w = weights
    c0, c1, hp, c2 = w.layer0_t.shape[1], w.layer1_t.shape[1], w.point_half_t.shape[1], w.last_t.shape[1]
    segments = len(counts)
    starts = np.zeros(segments + 1, np.int64)
    for s in range(segments):
        starts[s + 1] = starts[s] + counts[s]
    slo = 0
    while slo < segments:
        shi = slo + 1
        while shi < segments and starts[shi + 1] - starts[slo] <= w.chunk_rows:
            shi += 1
        a, r = starts[slo], starts[shi] - starts[slo]
        tt = layer0[:r]
        for i in range(r):
            x0, x1, x2 = points[a + i, 0], points[a + i, 1], points[a + i, 2]
            row = tt[i]
            for j in range(c0):
                row[j] = max(x0 * w.layer0_t[0, j] + x1 * w.layer0_t[1, j] + x2 * w.layer0_t[2, j]
                             + w.layer0_bias[j], np.float32(0.0))
        ff = layer1[:r]
        gemm(blas, tt, w.layer1_t, ff)
        gg = pooled1[: shi - slo]
        for s in range(slo, shi):
            acc = gg[s - slo]
            acc[:] = -np.inf
            for i in range(starts[s] - a, starts[s + 1] - a):
                row = ff[i]
                for j in range(c1):
                    acc[j] = max(acc[j], row[j])
        gpc = segment_half[: shi - slo]
        gemm(blas, gg, w.segment_half_t, gpc)
        hh = hidden[:r]
        gemm(blas, tt, w.point_half_t, hh)
        for s in range(slo, shi):
            seg = gpc[s - slo]
            for j in range(hp):
                seg[j] += w.segment_const[j]
            for i in range(starts[s] - a, starts[s + 1] - a):
                row = hh[i]
                for j in range(hp):
                    row[j] = max(row[j] + seg[j], np.float32(0.0))
        yy = last[:r]
        gemm(blas, hh, w.last_t, yy)
        for s in range(slo, shi):
            acc = out[s]
            if starts[s + 1] == starts[s]:
                acc[:] = 0.0
                continue
            acc[:] = yy[starts[s] - a]
            for i in range(starts[s] - a + 1, starts[s + 1] - a):
                row = yy[i]
                for j in range(c2):
                    acc[j] = max(acc[j], row[j])
            for j in range(c2):
                acc[j] += w.last_bias[j]
        slo = shi


@compiled(fastmath=True)
def fold(coarse, code_proj, weights, out, codes_per_row, codes_per_chunk, hidden_in, hidden_out, blas):
    """The folding step (one hidden layer): for every code ``s``, coarse point ``k`` and grid
    point ``g``, ``out = (coarse[s, k] + b2) + W2 relu(W1 h + b1)`` with ``h = relu(coarse[s, k]
    Wp^T + code_proj[s] + grid_proj[g])``, into ``out[s // m, (s % m) K G + k G + g]`` (``m``:
    ``codes_per_row``), ``codes_per_chunk`` codes per chunk (``hidden_in`` / ``hidden_out``:
    work arrays of ``codes_per_chunk K G`` rows). Fast-math: sums may be reassociated (float
    rounding in the last bits)."""
    w = weights
    codes, k_points = coarse.shape[0], coarse.shape[1]
    hdim, g_points, h1 = w.point_t.shape[1], w.grid_proj.shape[0], w.hidden_t.shape[1]
    m = codes_per_row
    base = np.empty(hdim, np.float32)
    for start in range(0, codes, codes_per_chunk):
        stop = min(start + codes_per_chunk, codes)
        r = (stop - start) * k_points * g_points
        row = 0
        for s in range(start, stop):
            cp = code_proj[s]
            for k in range(k_points):
                x0, x1, x2 = coarse[s, k, 0], coarse[s, k, 1], coarse[s, k, 2]
                for j in range(hdim):
                    base[j] = x0 * w.point_t[0, j] + x1 * w.point_t[1, j] + x2 * w.point_t[2, j] + cp[j]
                for gi in range(g_points):
                    gr = w.grid_proj[gi]
                    hr = hidden_in[row]
                    for j in range(hdim):
                        hr[j] = max(base[j] + gr[j], np.float32(0.0))
                    row += 1
        xs = hidden_out[:r]
        gemm(blas, hidden_in[:r], w.hidden_t, xs)
        row = 0
        for s in range(start, stop):
            q, p0 = s // m, (s % m) * k_points * g_points
            for k in range(k_points):
                sp0 = coarse[s, k, 0] + w.out_bias[0]
                sp1 = coarse[s, k, 1] + w.out_bias[1]
                sp2 = coarse[s, k, 2] + w.out_bias[2]
                for gi in range(g_points):
                    x = xs[row]
                    a0 = a1 = a2 = np.float32(0.0)
                    for j in range(h1):
                        v = max(x[j] + w.hidden_bias[j], np.float32(0.0))
                        a0 += w.out_weight[0, j] * v
                        a1 += w.out_weight[1, j] * v
                        a2 += w.out_weight[2, j] * v
                    o = p0 + k * g_points + gi
                    out[q, o, 0] = sp0 + a0
                    out[q, o, 1] = sp1 + a1
                    out[q, o, 2] = sp2 + a2
                    row += 1


@compiled()
def dense(x, weights, out, work, blas):
    """``x`` through fully connected layers (:class:`DenseWeights`), ReLU after every layer but
    the last, which writes ``out``. ``work``: at least :func:`_dense_floats` floats (the hidden
    layers' outputs)."""
    rows, layers = x.shape[0], len(weights.widths) - 1
    src = x
    wo = bo = 0
    for layer in range(layers):
        k, n = weights.widths[layer], weights.widths[layer + 1]
        if layer == layers - 1:
            dst = out
        else:  # the hidden layers alternate between the two halves of work
            dst, _ = _carve(work, (layer % 2) * (len(work) // 2), rows, n)
        gemm(blas, src, weights.weights_t[wo: wo + k * n].reshape((k, n)), dst)
        bias = weights.biases[bo: bo + n]
        relu = layer < layers - 1
        for i in range(rows):
            row = dst[i]
            for j in range(n):
                v = row[j] + bias[j]
                row[j] = max(v, np.float32(0.0)) if relu else v
        wo += k * n
        bo += n
        src = dst


@njit(inline="always")
def _dense_floats(weights, rows):
    """Work floats :func:`dense` carves for ``rows`` rows."""
    widths = weights.widths
    return 2 * (rows * widths[1:-1].max() + ALIGN) if len(widths) > 2 else 0


@compiled()
def sorted_counts(segment, segments):
    """Rows per segment id of a sorted ``segment`` (ids in ``[0, segments)``), or an empty
    array where it is not sorted or out of range (the caller takes the general path)."""
    counts = np.zeros(segments, np.int64)
    previous = 0
    for i in range(len(segment)):
        s = segment[i]
        if s < previous or s >= segments:
            return np.zeros(0, np.int64)
        counts[s] += 1
        previous = s
    return counts


@njit(inline="always")
def _encoder_floats(weights, counts):
    """Work floats :func:`_encode` carves."""
    w = weights
    most = max(w.chunk_rows, counts.max()) if len(counts) else w.chunk_rows
    widths = w.layer0_t.shape[1] + w.layer1_t.shape[1] + w.point_half_t.shape[1] + w.last_t.shape[1]
    return most * widths + len(counts) * (w.layer1_t.shape[1] + w.point_half_t.shape[1]) + 6 * ALIGN


@njit(inline="always")
def _encode(weights, points, counts, pooled, work, blas):
    """:func:`pcn_encode` with its work arrays carved from ``work``."""
    w = weights
    most = max(w.chunk_rows, counts.max()) if len(counts) else w.chunk_rows
    layer0, o = _carve(work, 0, most, w.layer0_t.shape[1])
    layer1, o = _carve(work, o, most, w.layer1_t.shape[1])
    hidden, o = _carve(work, o, most, w.point_half_t.shape[1])
    last, o = _carve(work, o, most, w.last_t.shape[1])
    pooled1, o = _carve(work, o, len(counts), w.layer1_t.shape[1])
    segment_half, o = _carve(work, o, len(counts), w.point_half_t.shape[1])
    pcn_encode(points, counts, w, pooled, layer0, layer1, hidden, last, pooled1, segment_half, blas)


@compiled()
def encoder_floats(weights, counts):
    """Work floats :func:`encode` needs (:func:`work_memory`)."""
    return _encoder_floats(weights, counts)


@compiled()
def encode(weights, points, counts, pooled, work, blas):
    """:func:`pcn_encode` on its own (``PCNEncoder``'s compiled path, its layers called one by
    one), its work arrays carved from ``work`` (:func:`encoder_floats` floats)."""
    _encode(weights, points, counts, pooled, work, blas)


@njit(inline="always")
def _fold_floats(weights, codes, coarse_points, codes_per_chunk):
    """Work floats :func:`_fold` carves for ``codes`` codes of ``coarse_points`` points."""
    w = weights
    rows = min(codes_per_chunk, codes) * coarse_points * w.grid_proj.shape[0]
    return rows * (w.point_t.shape[1] + w.hidden_t.shape[1]) + 2 * ALIGN


@njit(inline="always")
def _fold(coarse, code_proj, weights, out, codes_per_row, codes_per_chunk, work, blas):
    """:func:`fold` with its work arrays carved from ``work``."""
    w = weights
    rows = min(codes_per_chunk, coarse.shape[0]) * coarse.shape[1] * w.grid_proj.shape[0]
    hidden_in, o = _carve(work, 0, rows, w.point_t.shape[1])
    hidden_out, o = _carve(work, o, rows, w.hidden_t.shape[1])
    fold(coarse, code_proj, w, out, codes_per_row, codes_per_chunk, hidden_in, hidden_out, blas)


@compiled()
def fold_floats(weights, codes, coarse_points, codes_per_chunk):
    """Work floats :func:`fold_into` needs (:func:`work_memory`)."""
    return _fold_floats(weights, codes, coarse_points, codes_per_chunk)


@compiled()
def fold_into(coarse, code_proj, weights, out, codes_per_row, codes_per_chunk, work, blas):
    """:func:`fold` on its own (``FoldingDecoder``'s compiled path, the layers called one by one),
    its work arrays carved from ``work`` (:func:`fold_floats` floats)."""
    _fold(coarse, code_proj, weights, out, codes_per_row, codes_per_chunk, work, blas)


@njit(inline="always")
def _decoder_floats(weights, codes):
    """Work floats :func:`_decode` carves for ``codes`` codes."""
    w = weights
    coarse = codes * (3 * w.coarse_points + w.code_proj.widths[-1]) + 2 * ALIGN
    fold_work = _fold_floats(w.fold, codes, w.coarse_points, w.codes_per_chunk)
    return coarse + max(_dense_floats(w.coarse, codes), _dense_floats(w.code_proj, codes), fold_work) + ALIGN


@njit(inline="always")
def _decode(weights, code, codes_per_row, out, work, blas):
    """A folding decoder from ``code`` into ``out``."""
    w = weights
    s, k = code.shape[0], w.coarse_points
    coarse, o = _carve(work, 0, s, 3 * k)
    code_proj, o = _carve(work, o, s, w.code_proj.widths[-1])
    rest = work[(o + ALIGN - 1) // ALIGN * ALIGN:]
    dense(code, w.coarse, coarse, rest, blas)
    dense(code, w.code_proj, code_proj, rest, blas)
    _fold(coarse.reshape((s, k, 3)), code_proj, w.fold, out, codes_per_row, w.codes_per_chunk, rest, blas)


@compiled()
def network_floats(weights, counts, local_counts, gathered):
    """Work floats :func:`pointpncnet_infer` needs for ``len(counts)`` instances and ``gathered``
    (point, octant) memberships (:func:`work_memory`)."""
    w = weights
    b = len(counts)
    codes = b * REGIONS
    embed = w.global_encoder.last_t.shape[1]
    kept = b * embed * 2 + codes * (2 * embed + REGIONS + 1) + gathered * 3 + 7 * ALIGN  # the carving below
    return kept + max(_encoder_floats(w.global_encoder, counts), _encoder_floats(w.local_encoder, local_counts),
                      _decoder_floats(w.global_decoder, b), _decoder_floats(w.local_decoder, codes),
                      _dense_floats(w.attention, codes))


@compiled()
def pointpncnet_infer(points, counts, point_index, local_counts, weights, out, present, work, blas):
    """PointPnCNet's whole inference (``PointPnCNetNet.forward`` on the compiled path) in one
    call, no Python between its steps: the global encoder over ``points`` (``counts`` per
    instance, sorted), the local one over the gathered ``points[point_index]`` (``local_counts``
    per instance and octant), the attention-weighted fusion, and both folding decoders into
    ``out`` ``(B, Mg + 8 Ml, 3)`` (the global points, then the octants'); ``present`` ``(B, 8)``
    gets the octants with at least ``weights.min_region_points`` points. ``work``: float32 work
    memory for every intermediate, :func:`network_floats` floats (:func:`work_memory`)."""
    w = weights
    b = len(counts)
    codes = b * REGIONS
    embed = w.global_encoder.last_t.shape[1]
    e_g, o = _carve(work, 0, b, embed)
    fused, o = _carve(work, o, b, embed)
    e_l, o = _carve(work, o, codes, embed)
    code, o = _carve(work, o, codes, embed + REGIONS)
    logits, o = _carve(work, o, codes, 1)
    local_points, o = _carve(work, o, len(point_index), 3)
    phase = work[(o + ALIGN - 1) // ALIGN * ALIGN:]  # each step's own work memory

    _encode(w.global_encoder, points, counts, e_g, phase, blas)
    for i in range(len(point_index)):
        if not 0 <= point_index[i] < len(points):
            raise IndexError("pointpncnet_infer: a point index out of range")
        local_points[i] = points[point_index[i]]
    _encode(w.local_encoder, local_points, local_counts, e_l, phase, blas)

    # attention over the present octants (a softmax), its weighted code max-fused with the global one
    dense(e_l, w.attention, logits, phase, blas)
    fused[:] = e_g
    octant_weights = np.empty(REGIONS, np.float32)
    for s in range(b):
        top = np.float32(-np.inf)
        for r in range(REGIONS):
            present[s, r] = local_counts[s * REGIONS + r] >= w.min_region_points
            if present[s, r]:
                top = max(top, logits[s * REGIONS + r, 0])
        if top == -np.inf:  # no octant: the global code alone
            continue
        total = np.float32(0.0)
        for r in range(REGIONS):
            octant_weights[r] = np.exp(logits[s * REGIONS + r, 0] - top) if present[s, r] else np.float32(0.0)
            total += octant_weights[r]
        for r in range(REGIONS):
            octant_weights[r] /= total
        for j in range(embed):
            acc = np.float32(0.0)
            for r in range(REGIONS):
                acc += octant_weights[r] * e_l[s * REGIONS + r, j]
            fused[s, j] = max(fused[s, j], acc)

    # the octants' codes: the fused code and the octant's one-hot
    for s in range(b):
        for r in range(REGIONS):
            row = code[s * REGIONS + r]
            row[:embed] = fused[s]
            row[embed:] = 0.0
            row[embed + r] = 1.0
    global_points = w.global_decoder.coarse_points * w.global_decoder.fold.grid_proj.shape[0]
    _decode(w.global_decoder, fused, 1, out[:, :global_points], phase, blas)
    _decode(w.local_decoder, code, REGIONS, out[:, global_points:], phase, blas)


@compiled()
def octant_pairs(points, lengths, overlap):
    """Every (point, octant) membership of a packed batch (``lengths`` points per instance), as
    ``(point index, instance * 8 + octant)`` grouped by the latter, ascending (a counting sort;
    within a group a point's own octant's members come first, then the points it shares from
    the overlap bands, each in point order). A point lies in its own octant (``bit0 = x >= 0``,
    ``bit1 = y >= 0``, ``bit2 = z >= 0``) and, within ``overlap`` of a coordinate plane, in the
    octants across it: the memberships of :func:`pcc_ros.geometry.partitions.octant_masks`
    (the comparisons in the points' precision)."""
    p, instances = points.shape[0], len(lengths)
    counts = np.zeros(instances * 8 + 1, np.int64)
    key = np.empty(p, np.int64)  # instance * 8 + own octant
    shared = np.zeros(p, np.int64)  # bit o: also in octant o
    zero, below = points.dtype.type(0), -overlap
    i = 0
    for s in range(instances):
        for _ in range(lengths[s]):
            x, y, z = points[i, 0], points[i, 1], points[i, 2]
            own = (1 if x >= zero else 0) | (2 if y >= zero else 0) | (4 if z >= zero else 0)
            key[i] = s * 8 + own
            counts[key[i] + 1] += 1
            px, py, pz = x >= below, y >= below, z >= below  # may be on the >= 0 side
            nx, ny, nz = x < overlap, y < overlap, z < overlap  # may be on the < 0 side
            if (px and nx) or (py and ny) or (pz and nz):
                for o in range(8):
                    if o != own and (px if o & 1 else nx) and (py if o & 2 else ny) and (pz if o & 4 else nz):
                        shared[i] |= 1 << o
                        counts[s * 8 + o + 1] += 1
            i += 1
    for c in range(1, len(counts)):
        counts[c] += counts[c - 1]
    point_index = np.empty(counts[-1], np.int64)
    local = np.empty(counts[-1], np.int64)
    fill = counts[:-1].copy()
    for i in range(p):
        point_index[fill[key[i]]] = i
        local[fill[key[i]]] = key[i]
        fill[key[i]] += 1
    for i in range(p):
        if shared[i]:
            base = key[i] - key[i] % 8
            for o in range(8):
                if shared[i] >> o & 1:
                    point_index[fill[base + o]] = i
                    local[fill[base + o]] = base + o
                    fill[base + o] += 1
    return point_index, local


def warm_up(blas=None) -> None:
    """Compile every kernel for the argument types inference passes (numba compiles on first
    call, or loads its disk cache: seconds the first time on a machine, about 0.3 s after), on
    tiny arrays, so a model's first real batch does not pay for it: ``fold_into`` for an output of
    its own and for a view of a bigger one (PointPnCNet's global points and octants), with the
    products on ``blas``'s route (default: :func:`pcc_ros.models.blas.route`)."""
    if not AVAILABLE:
        return
    blas = blas_routes.route() if blas is None else blas
    f32 = np.float32
    rng = np.random.default_rng(0)
    points = rng.normal(size=(6, 3)).astype(f32)
    octant_pairs(points, np.array([4, 2], np.int64), f32(0.005))
    counts = sorted_counts(np.array([0, 0, 0, 0, 1, 1], np.int64), 2)

    def w(*shape):
        return rng.normal(size=shape).astype(f32)

    encoder = EncoderWeights(w(3, 2), w(2), w(2, 3), w(2, 3), w(3, 3), w(3), w(3, 4), w(4), 4)
    encode(encoder, points, counts, np.empty((2, 4), f32), np.empty(encoder_floats(encoder, counts), f32), blas)
    folding = FoldWeights(w(2, 5), w(3, 5), w(5, 4), w(4), w(3, 4), w(3))
    for out in (np.empty((2, 4, 3), f32), np.empty((2, 9, 3), f32)[:, 5:]):
        fold_into(w(2, 2, 3), w(2, 5), folding, out, 1, 1, np.empty(fold_floats(folding, 2, 2, 1), f32), blas)
