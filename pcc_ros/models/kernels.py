"""Compiled CPU inference loops of the PCN encoder and the folding decoder (numba).

Why: in eager PyTorch every step of a chunk is an operator call (5-10 us of dispatch) and a
pass through memory: the max-pooling scatters, the ReLUs, the folding decoder's broadcast adds
and its 3-wide output layer (a matrix product at a fifth of the matmul rate) took a fifth of
the network's time (``pcc bench complete``). Here a chunk's matrix products are the same MKL
``sgemm`` ``torch.mm`` runs (libtorch's own, called from the compiled code, the calling
thread's MKL thread count set to torch's), and the work between them is fused loops over the
chunk's rows while they are in cache (bias, ReLU, max-pooling, broadcast add, the 3-wide output
layer with its residual), with no Python between them. The functions are the layers' inference
paths (``layers.PCNEncoder._forward_compiled``, ``layers.FoldingDecoder._fold_compiled``; the
torch-operator versions beside them stay for other layer shapes, the GPU and the comparison),
same weights, same folded constants; float rounding differs in the last bits (``pcc bench
complete`` and the tests compare them with the original path).

:func:`pointpncnet_infer` runs PointPnCNet's whole network in one call (both encoders, the
octant gather, the attention and fusion, both decoders' fully connected layers and folding):
called layer by layer, the Python and torch operators between the kernels, run while the
caches are cold from the kernel before, cost 4-5 % of the network's time (``pcc bench complete``,
``fast_layers``).

Used on CPU float32 inference only (:func:`pcc_ros.models.layers.compiled_kernels` switches them
off); compiled on first use and cached on disk (:func:`pcc_ros.jit.compiled`; :func:`warm_up` at
model load).
"""

from __future__ import annotations

import ctypes
import os
import threading

import numpy as np
import torch
from numba import njit, types

from pcc_ros.jit import compiled


def _libtorch_blas():
    """libtorch's Fortran ``sgemm_`` (MKL on x86) as a numba external function (resolved by name
    when a kernel is linked, so the kernels can be cached) and MKL's per-thread thread count, or
    ``(None, None)`` where this torch build has no such symbols."""
    path = os.path.join(os.path.dirname(torch.__file__), "lib", "libtorch_cpu.so")
    try:
        lib = ctypes.CDLL(path)
        lib.sgemm_  # noqa: B018  (raises AttributeError where absent)
        threads = ctypes.CFUNCTYPE(ctypes.c_int, ctypes.c_int)(("MKL_Set_Num_Threads_Local", lib))  # by value
    except (OSError, AttributeError):
        return None, None
    import llvmlite.binding

    llvmlite.binding.load_library_permanently(path)
    return types.ExternalFunction("sgemm_", types.void(*([types.intp] * 13))), threads


_sgemm, _set_threads = _libtorch_blas()
AVAILABLE = _sgemm is not None


_threads = threading.local()


def set_threads(n: int) -> None:
    """MKL's thread count for the calling thread's products (torch's intra-op threads); the
    ctypes call is made only when the count changes, not once per kernel call."""
    if _set_threads is not None and getattr(_threads, "n", None) != n:
        _set_threads(int(n))
        _threads.n = n


@njit(inline="always")
def _mm_args():
    """:func:`_mm`'s argument memory (sgemm takes every argument by reference): sizes and strides,
    alpha and beta, and the transpose flag "N" (none)."""
    return np.empty(6, np.int32), np.empty(2, np.float32), np.full(1, 78, np.uint8)


@njit(inline="always")
def _mm(a, b, c, ints, floats, chars):
    """``c = a @ b`` (row-major, unit inner strides): column-major ``c^T = b^T a^T``."""
    m, k = a.shape
    n = b.shape[1]
    ints[0], ints[1], ints[2] = n, m, k
    ints[3], ints[4], ints[5] = b.strides[0] // 4, a.strides[0] // 4, c.strides[0] // 4
    floats[0], floats[1] = 1.0, 0.0
    _sgemm(chars.ctypes.data, chars.ctypes.data, ints[0:].ctypes.data, ints[1:].ctypes.data,
           ints[2:].ctypes.data, floats[0:].ctypes.data, b.ctypes.data, ints[3:].ctypes.data,
           a.ctypes.data, ints[4:].ctypes.data, floats[1:].ctypes.data, c.ctypes.data, ints[5:].ctypes.data)


@compiled()
def pcn_encode(points, counts, rows, w0t, b0, w1t, wct, wst, const, w2t, b2, out, t, f, h, y, g, gp):
    """The PCN encoder's composed inference path (points sorted by segment, ``counts`` per
    segment) on chunks of whole segments of about ``rows`` rows (one longer segment alone):
    ``t = relu(p W0^T + b0)``, ``g = max_seg(t W1^T)``, ``h = relu(t Wc + (g Ws + const)[seg])``,
    ``out = max_seg(h W2^T) + b2`` (0 for an empty segment).
    ``t, f, h, y``: work arrays of ``max(rows, largest segment)`` rows; ``g, gp``: of a row per
    segment."""
    ints, floats, chars = _mm_args()
    c0, c1, hp, c2 = w0t.shape[1], w1t.shape[1], wct.shape[1], w2t.shape[1]
    segments = len(counts)
    starts = np.zeros(segments + 1, np.int64)
    for s in range(segments):
        starts[s + 1] = starts[s] + counts[s]
    slo = 0
    while slo < segments:
        shi = slo + 1
        while shi < segments and starts[shi + 1] - starts[slo] <= rows:
            shi += 1
        a, r = starts[slo], starts[shi] - starts[slo]
        tt = t[:r]
        for i in range(r):
            x0, x1, x2 = points[a + i, 0], points[a + i, 1], points[a + i, 2]
            row = tt[i]
            for j in range(c0):
                row[j] = max(x0 * w0t[0, j] + x1 * w0t[1, j] + x2 * w0t[2, j] + b0[j], np.float32(0.0))
        ff = f[:r]
        _mm(tt, w1t, ff, ints, floats, chars)
        gg = g[: shi - slo]
        for s in range(slo, shi):
            acc = gg[s - slo]
            acc[:] = -np.inf
            for i in range(starts[s] - a, starts[s + 1] - a):
                row = ff[i]
                for j in range(c1):
                    acc[j] = max(acc[j], row[j])
        gpc = gp[: shi - slo]
        _mm(gg, wst, gpc, ints, floats, chars)
        hh = h[:r]
        _mm(tt, wct, hh, ints, floats, chars)
        for s in range(slo, shi):
            seg = gpc[s - slo]
            for j in range(hp):
                seg[j] += const[j]
            for i in range(starts[s] - a, starts[s + 1] - a):
                row = hh[i]
                for j in range(hp):
                    row[j] = max(row[j] + seg[j], np.float32(0.0))
        yy = y[:r]
        _mm(hh, w2t, yy, ints, floats, chars)
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
                acc[j] += b2[j]
        slo = shi


@compiled(fastmath=True)
def fold(coarse, wpt, code_proj, grid, w1t, b1, w2, b2, out, m, step, hbuf, xbuf):
    """The folding step (one hidden layer): for every code ``s``, coarse point ``k`` and grid
    point ``g``, ``out = (coarse[s, k] + b2) + W2 relu(W1 h + b1)`` with ``h = relu(coarse[s, k]
    Wp^T + code_proj[s] + grid[g])``, into ``out[s // m, (s % m) K G + k G + g]``, ``step``
    codes per chunk (``hbuf`` / ``xbuf``: work arrays of ``step K G`` rows). Fast-math: sums may
    be reassociated (float rounding in the last bits)."""
    ints, floats, chars = _mm_args()
    codes, k_points = coarse.shape[0], coarse.shape[1]
    hdim, g_points, h1 = wpt.shape[1], grid.shape[0], w1t.shape[1]
    base = np.empty(hdim, np.float32)
    for start in range(0, codes, step):
        stop = min(start + step, codes)
        r = (stop - start) * k_points * g_points
        row = 0
        for s in range(start, stop):
            cp = code_proj[s]
            for k in range(k_points):
                x0, x1, x2 = coarse[s, k, 0], coarse[s, k, 1], coarse[s, k, 2]
                for j in range(hdim):
                    base[j] = x0 * wpt[0, j] + x1 * wpt[1, j] + x2 * wpt[2, j] + cp[j]
                for gi in range(g_points):
                    gr = grid[gi]
                    hr = hbuf[row]
                    for j in range(hdim):
                        hr[j] = max(base[j] + gr[j], np.float32(0.0))
                    row += 1
        xs = xbuf[:r]
        _mm(hbuf[:r], w1t, xs, ints, floats, chars)
        row = 0
        for s in range(start, stop):
            q, p0 = s // m, (s % m) * k_points * g_points
            for k in range(k_points):
                sp0, sp1, sp2 = coarse[s, k, 0] + b2[0], coarse[s, k, 1] + b2[1], coarse[s, k, 2] + b2[2]
                for gi in range(g_points):
                    x = xs[row]
                    a0 = a1 = a2 = np.float32(0.0)
                    for j in range(h1):
                        v = max(x[j] + b1[j], np.float32(0.0))
                        a0 += w2[0, j] * v
                        a1 += w2[1, j] * v
                        a2 += w2[2, j] * v
                    o = p0 + k * g_points + gi
                    out[q, o, 0] = sp0 + a0
                    out[q, o, 1] = sp1 + a1
                    out[q, o, 2] = sp2 + a2
                    row += 1


#: Floats :func:`_carve` may skip to align a view (a cache line).
ALIGN = 16


@njit(inline="always")
def _carve(work, offset, rows, cols):
    """A ``(rows, cols)`` view of ``work`` from ``offset`` or up to :data:`ALIGN` floats later (a
    cache-line aligned start: misaligned operands slow the products), and the offset after it."""
    offset += (ALIGN - (work.ctypes.data // 4 + offset) % ALIGN) % ALIGN
    return work[offset: offset + rows * cols].reshape((rows, cols)), offset + rows * cols


@compiled()
def dense(x, weights, biases, dims, out, work):
    """``x`` through fully connected layers: layer ``l`` maps ``dims[l]`` to ``dims[l + 1]``
    columns, its transposed weight ``(dims[l], dims[l + 1])`` and its bias stored one after the
    other in the flat ``weights`` / ``biases``; ReLU after every layer but the last, which
    writes ``out``. ``work``: at least ``2 * (rows * max(dims[1:-1]) + ALIGN)`` floats (hidden layers)."""
    ints, floats, chars = _mm_args()
    rows, layers = x.shape[0], len(dims) - 1
    src = x
    wo = bo = 0
    for layer in range(layers):
        k, n = dims[layer], dims[layer + 1]
        if layer == layers - 1:
            dst = out
        else:  # the hidden layers alternate between the two halves of work
            dst, _ = _carve(work, (layer % 2) * (len(work) // 2), rows, n)
        _mm(src, weights[wo: wo + k * n].reshape((k, n)), dst, ints, floats, chars)
        bias = biases[bo: bo + n]
        relu = layer < layers - 1
        for i in range(rows):
            row = dst[i]
            for j in range(n):
                v = row[j] + bias[j]
                row[j] = max(v, np.float32(0.0)) if relu else v
        wo += k * n
        bo += n
        src = dst


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
def _encoder_floats(enc, most, segments):
    """Work floats :func:`_encode` carves (``most``: its chunk's rows)."""
    return most * (enc[0].shape[1] + enc[2].shape[1] + enc[3].shape[1] + enc[6].shape[1]) + \
        segments * (enc[2].shape[1] + enc[3].shape[1]) + 6 * ALIGN


@njit(inline="always")
def _encode(enc, points, counts, rows, most, pooled, work):
    """:func:`pcn_encode` with its work arrays carved from ``work``."""
    t, o = _carve(work, 0, most, enc[0].shape[1])
    f, o = _carve(work, o, most, enc[2].shape[1])
    h, o = _carve(work, o, most, enc[3].shape[1])
    y, o = _carve(work, o, most, enc[6].shape[1])
    g, o = _carve(work, o, len(counts), enc[2].shape[1])
    gp, o = _carve(work, o, len(counts), enc[3].shape[1])
    pcn_encode(points, counts, rows, enc[0], enc[1], enc[2], enc[3], enc[4], enc[5], enc[6], enc[7], pooled,
               t, f, h, y, g, gp)


@compiled()
def encode(enc, points, counts, rows, pooled, work):
    """:func:`pcn_encode` on its own (``PCNEncoder``'s compiled path, its layers called one by
    one): its work arrays carved from ``work``, replaced by a bigger array where too small;
    returns the one used, for the caller to keep."""
    most = max(rows, counts.max())
    need = _encoder_floats(enc, most, len(counts))
    if len(work) < need:
        work = np.empty(need + need // 4, np.float32)
    _encode(enc, points, counts, rows, most, pooled, work)
    return work


@njit(inline="always")
def _fold_floats(fw, codes, k, step):
    """Work floats :func:`_fold` carves for ``codes`` codes of ``k`` coarse points."""
    return min(step, codes) * k * fw[0].shape[0] * (fw[1].shape[1] + fw[2].shape[1]) + 2 * ALIGN


@njit(inline="always")
def _fold(coarse, proj, fw, out, m, step, work):
    """:func:`fold` with its work arrays carved from ``work``; ``fw``: its ``grid, wpt, w1t, b1,
    w2, b2``."""
    s, k = coarse.shape[0], coarse.shape[1]
    rows = min(step, s) * k * fw[0].shape[0]
    hbuf, o = _carve(work, 0, rows, fw[1].shape[1])
    xbuf, o = _carve(work, o, rows, fw[2].shape[1])
    fold(coarse, fw[1], proj, fw[0], fw[2], fw[3], fw[4], fw[5], out, m, step, hbuf, xbuf)


@compiled()
def fold_into(coarse, proj, fw, out, m, step, work):
    """:func:`fold` on its own (``FoldingDecoder``'s compiled path, the layers called one by one):
    its work arrays carved from ``work``, replaced by a bigger array where too small; returns the
    one used, for the caller to keep."""
    need = _fold_floats(fw, coarse.shape[0], coarse.shape[1], step)
    if len(work) < need:
        work = np.empty(need + need // 4, np.float32)
    _fold(coarse, proj, fw, out, m, step, work)
    return work


@njit(inline="always")
def _decoder_floats(dec, codes, step):
    """Work floats :func:`_decode` carves for ``codes`` codes."""
    fc, k = dec[2], dec[2][-1] // 3
    hidden = 2 * (codes * fc[1:-1].max() + ALIGN) if len(fc) > 2 else 0
    return codes * (3 * k + dec[7].shape[1]) + max(hidden, _fold_floats(dec[6:], codes, k, step)) + 2 * ALIGN


@njit(inline="always")
def _decode(dec, code, step, m, out, work):
    """A folding decoder (``dec``: see :func:`pointpncnet_infer`) from ``code`` into ``out``."""
    s, k = code.shape[0], dec[2][-1] // 3
    coarse, o = _carve(work, 0, s, 3 * k)
    proj, o = _carve(work, o, s, dec[7].shape[1])
    rest = work[o:]
    dense(code, dec[0], dec[1], dec[2], coarse, rest)
    dense(code, dec[3], dec[4], dec[5], proj, rest)
    _fold(coarse.reshape((s, k, 3)), proj, dec[6:], out, m, step, rest)


@compiled()
def pointpncnet_infer(points, counts, point_index, local_counts, min_points, genc, grows, lenc, lrows,
                      attention, gdec, gstep, ldec, lstep, out, present, work):
    """PointPnCNet's whole inference (``PointPnCNetNet.forward`` on the fast path) in one call,
    no Python between its steps: the global encoder over ``points`` (``counts`` per instance,
    sorted), the local one over the gathered ``points[point_index]`` (``local_counts`` per
    instance and octant), the attention-weighted fusion, and both folding decoders into ``out``
    ``(B, Mg + 8 Ml, 3)`` (the global points, then the octants'); ``present`` ``(B, 8)`` gets the
    octants with at least ``min_points`` points.

    ``genc`` / ``lenc``: :func:`pcn_encode`'s weights, ``grows`` / ``lrows`` its chunk rows;
    ``attention``: :func:`dense`'s ``(weights, biases, dims)``; ``gdec`` / ``ldec``: the fully
    connected layers' and the code projection's ``(weights, biases, dims)`` then :func:`fold`'s
    ``grid, wpt, w1t, b1, w2, b2``; ``gstep`` / ``lstep``: codes per folding chunk. ``work``:
    float32 work memory for every intermediate, replaced by a bigger array where too small;
    returns the one used, for the caller to keep (fresh memory costs page faults on every call,
    and its release stalls the other threads of the process)."""
    b, regions = len(counts), 8
    codes = b * regions
    most_g, most_l = max(grows, counts.max()), max(lrows, local_counts.max())
    embed = genc[6].shape[1]
    kept = b * embed * 2 + codes * (2 * embed + regions + 1) + len(point_index) * 3 + 7 * ALIGN  # the carving below
    need = kept + max(_encoder_floats(genc, most_g, b), _encoder_floats(lenc, most_l, codes),
                      _decoder_floats(gdec, b, gstep), _decoder_floats(ldec, codes, lstep),
                      2 * (codes * attention[2][1:].max() + ALIGN))
    if len(work) < need:
        work = np.empty(need + need // 4, np.float32)
    e_g, o = _carve(work, 0, b, embed)
    fused, o = _carve(work, o, b, embed)
    e_l, o = _carve(work, o, codes, embed)
    code, o = _carve(work, o, codes, embed + regions)
    logits, o = _carve(work, o, codes, 1)
    local_points, o = _carve(work, o, len(point_index), 3)
    phase = work[o:]  # each step's own work memory

    _encode(genc, points, counts, grows, most_g, e_g, phase)
    for i in range(len(point_index)):
        if not 0 <= point_index[i] < len(points):
            raise IndexError("pointpncnet_infer: a point index out of range")
        local_points[i] = points[point_index[i]]
    _encode(lenc, local_points, local_counts, lrows, most_l, e_l, phase)

    # attention over the present octants (a softmax), its weighted code max-fused with the global one
    dense(e_l, attention[0], attention[1], attention[2], logits, phase)
    fused[:] = e_g
    weights = np.empty(regions, np.float32)
    for s in range(b):
        top = np.float32(-np.inf)
        for r in range(regions):
            present[s, r] = local_counts[s * regions + r] >= min_points
            if present[s, r]:
                top = max(top, logits[s * regions + r, 0])
        if top == -np.inf:  # no octant: the global code alone
            continue
        total = np.float32(0.0)
        for r in range(regions):
            weights[r] = np.exp(logits[s * regions + r, 0] - top) if present[s, r] else np.float32(0.0)
            total += weights[r]
        for r in range(regions):
            weights[r] /= total
        for j in range(embed):
            acc = np.float32(0.0)
            for r in range(regions):
                acc += weights[r] * e_l[s * regions + r, j]
            fused[s, j] = max(fused[s, j], acc)

    # the octants' codes: the fused code and the octant's one-hot
    for s in range(b):
        for r in range(regions):
            row = code[s * regions + r]
            row[:embed] = fused[s]
            row[embed:] = 0.0
            row[embed + r] = 1.0
    mg = gdec[2][-1] // 3 * gdec[6].shape[0]
    _decode(gdec, fused, gstep, 1, out[:, :mg], phase)
    _decode(ldec, code, lstep, regions, out[:, mg:], phase)
    return work


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


def warm_up() -> None:
    """Compile every kernel for the argument types inference passes (numba compiles on first
    call, or loads its disk cache: seconds the first time on a machine, about 0.3 s after), on
    tiny arrays, so a model's first real batch does not pay for it: ``fold_into`` for an output of
    its own and for a view of a bigger one (PointPnCNet's global points and octants)."""
    if not AVAILABLE:
        return
    f32 = np.float32
    rng = np.random.default_rng(0)
    points = rng.normal(size=(6, 3)).astype(f32)
    octant_pairs(points, np.array([4, 2], np.int64), f32(0.005))
    sorted_counts(np.array([0, 0, 1], np.int64), 2)

    def w(*shape):
        return rng.normal(size=shape).astype(f32)

    encode((w(3, 2), w(2), w(2, 3), w(2, 3), w(3, 3), w(3), w(3, 4), w(4)), points, np.array([4, 2], np.int64), 4,
           np.empty((2, 4), f32), np.empty(0, f32))
    for out in (np.empty((2, 4, 3), f32), np.empty((2, 9, 3), f32)[:, 5:]):
        fold_into(w(2, 2, 3), w(2, 5), (w(2, 5), w(3, 5), w(5, 4), w(4), w(3, 4), w(3)), out, 1, 1, np.empty(0, f32))
