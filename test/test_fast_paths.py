"""The fast inference paths return what the reference (original) paths return.

Speed is measured by ``pcc bench complete`` / ``pcc bench pipeline``, never here; these
tests only pin the values.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np
import pytest
import torch

from pcc_ros.models import default_checkpoint, inference, layers, load_completer
from pcc_ros.models.inference import set_inference_path
from pcc_ros.models.layers import FoldingDecoder, PCNEncoder, segment_max


@pytest.fixture(autouse=True, params=[True, False], ids=["kernels", "no-kernels"])
def _compiled_loops(request, monkeypatch):
    """Every test here runs where the compiled CPU loops (pcc_ros.models.kernels) can run and
    where they cannot (numba's BLAS missing: the capability check says no), so the default
    ``auto`` path takes the compiled loops or the same steps as torch operators. Where the compiled
    loops cannot run on this machine, the kernels variant skips saying so instead of passing on
    the operators."""
    if request.param and not inference.kernels_available():
        pytest.skip("compiled CPU kernels unavailable here (pcc_ros.models.inference.kernels_available() "
                    "is False: no numba BLAS / MKL sgemm in this torch build)")
    if not request.param:
        monkeypatch.setattr(inference, "kernels_available", lambda: False)
    yield request.param and inference.kernels_available()


@contextmanager
def on_path(path: str, *models) -> Iterator[None]:
    """``models`` (modules or completers) on inference ``path`` inside the block, on their own after."""
    before = [m.inference_path for m in models]
    for m in models:
        if isinstance(m, torch.nn.Module):
            set_inference_path(m, path)
        else:
            m.inference_path = path
    try:
        yield
    finally:
        for m, old in zip(models, before):
            if isinstance(m, torch.nn.Module):
                set_inference_path(m, old)
            else:
                m.inference_path = old


def _packed(rng: np.random.Generator, sizes: list[int]) -> tuple[torch.Tensor, torch.Tensor]:
    points = torch.from_numpy(rng.normal(size=(sum(sizes), 3)).astype(np.float32))
    segment = torch.from_numpy(np.repeat(np.arange(len(sizes)), sizes))
    return points, segment


@pytest.mark.parametrize("channels", [1, 7, 64])
def test_scatter_segment_max_is_bit_identical_to_segment_reduce(channels):
    rng = np.random.default_rng(channels)
    sizes = [5, 0, 1, 300, 0, 17, 2]  # empty segments in the middle and at the end of nothing
    feats = torch.from_numpy(rng.normal(size=(sum(sizes), channels)).astype(np.float32)) - 3.0  # mostly < 0
    seg = torch.from_numpy(np.repeat(np.arange(len(sizes)), sizes))
    fast = segment_max(feats, seg, len(sizes) + 1, method="scatter")
    ref = segment_max(feats, seg, len(sizes) + 1, method="segment_reduce")
    assert torch.equal(fast, ref)
    assert torch.equal(fast[1], torch.zeros(channels)) and torch.equal(fast[-1], torch.zeros(channels))
    assert torch.equal(segment_max(feats, seg, len(sizes) + 1), fast)  # the default: the scatter
    with pytest.raises(ValueError, match="unknown method"):
        segment_max(feats, seg, 3, method="bogus")


def test_scatter_segment_max_gradient_matches_segment_reduce():
    rng = np.random.default_rng(1)
    base = torch.from_numpy(rng.normal(size=(40, 6)).astype(np.float32))
    seg = torch.from_numpy(np.repeat(np.arange(4), [10, 5, 0, 25]))
    grads = []
    for method in ("scatter", "segment_reduce"):
        x = base.clone().requires_grad_(True)
        (segment_max(x, seg, 4, method=method) * torch.arange(1.0, 7.0)).sum().backward()
        grads.append(x.grad)
    assert torch.equal(grads[0], grads[1])


@pytest.mark.parametrize("widths1", [[8, 16], [16, 8], [16]])  # composed point half (8 < 16) or not
@pytest.mark.parametrize("widths2", [[32, 12], [12], [16, 24, 12]])
def test_chunked_encoder_equals_reference(monkeypatch, widths1, widths2):
    """Segments longer than a chunk, empty segments, one or several mlp1 / mlp2 layers."""
    monkeypatch.setattr(layers, "CHUNK_BYTES", 2000)  # a few rows per chunk
    torch.manual_seed(0)
    enc = PCNEncoder(widths1, widths2)
    points, segment = _packed(np.random.default_rng(2), [3, 0, 20, 1, 9, 0])
    with torch.no_grad():
        fast = enc(points, segment, 7)
        with on_path("reference", enc):
            ref = enc(points, segment, 7)
    assert fast.shape == ref.shape == (7, widths2[-1])
    torch.testing.assert_close(fast, ref, rtol=1e-5, atol=1e-6)
    assert torch.equal(fast[[1, 5, 6]], torch.zeros(3, widths2[-1]))
    with torch.no_grad():  # no points at all
        assert torch.equal(enc(points[:0], segment[:0], 2), torch.zeros(2, widths2[-1]))


def test_training_path_is_differentiable_and_equals_reference():
    torch.manual_seed(0)
    enc = PCNEncoder([8, 16], [32, 12])
    points, segment = _packed(np.random.default_rng(3), [4, 11, 6])
    fast = enc(points, segment, 3)  # grad enabled: the unchunked path with the scatter max
    assert fast.requires_grad
    fast.sum().backward()
    fast_grad = [p.grad.clone() for p in enc.parameters()]
    enc.zero_grad()
    with on_path("reference", enc):
        ref = enc(points, segment, 3)
        ref.sum().backward()
    torch.testing.assert_close(fast, ref)
    for a, p in zip(fast_grad, enc.parameters()):
        torch.testing.assert_close(a, p.grad)


def test_chunked_folding_decoder_equals_reference(monkeypatch):
    monkeypatch.setattr(layers, "CHUNK_BYTES", 2800)  # 30 rows (23 floats each) // 20 points = 1 instance
    torch.manual_seed(0)
    dec = FoldingDecoder(12, [16], num_coarse=5, grid_size=2, fold_widths=[10, 10], grid_scale=0.05)
    code = torch.randn(3, 12)
    with torch.no_grad():
        coarse, fine = dec(code)
        with on_path("reference", dec):
            ref_coarse, ref_fine = dec(code)
    assert torch.equal(coarse, ref_coarse)
    torch.testing.assert_close(fine, ref_fine, rtol=1e-6, atol=1e-7)


def test_folding_decoder_writes_into_a_strided_output(monkeypatch):
    """``out``: a view of a bigger tensor, one code per row or several (the octants of a car)."""
    monkeypatch.setattr(layers, "CHUNK_BYTES", 2800)  # several chunks
    torch.manual_seed(0)
    dec = FoldingDecoder(12, [16], num_coarse=5, grid_size=2, fold_widths=[10, 10], grid_scale=0.05)
    code = torch.randn(6, 12)
    with torch.no_grad(), on_path("reference", dec):
        _, ref = dec(code)  # (6, 20, 3)
    for per_row in (1, 2, 3):
        for fast in (True, False):
            big = torch.full((6 // per_row, 7 + per_row * 20, 3), 9.0)
            out = big[:, 7:]  # strided: the first 7 points of each row belong to someone else
            with torch.no_grad(), on_path("auto" if fast else "reference", dec):
                _, fine = dec(code, out)
            assert fine is out
            torch.testing.assert_close(out.reshape(6, 20, 3), ref, rtol=1e-6, atol=1e-7)
            assert torch.equal(big[:, :7], torch.full((6 // per_row, 7, 3), 9.0))  # untouched
    with torch.no_grad(), pytest.raises(ValueError, match="out of shape"):
        dec(code, torch.empty(4, 30, 3))  # 6 codes do not split into 4 rows


def test_encoder_folded_constants_follow_parameter_updates():
    """The composed weight and constant are kept between calls, until a parameter changes in place."""
    torch.manual_seed(0)
    enc = PCNEncoder([8, 16], [32, 12])
    points, segment = _packed(np.random.default_rng(12), [7, 20, 3])
    with torch.no_grad():
        first = enc(points, segment, 3)
        for p in (enc.point_proj.weight, enc.mlp1.net[-1].bias, enc.segment_proj.weight):
            p.mul_(1.5)  # what an optimizer step or load_state_dict does: in place
            fast = enc(points, segment, 3)
            with on_path("reference", enc):
                ref = enc(points, segment, 3)
            torch.testing.assert_close(fast, ref, rtol=1e-5, atol=1e-6)
        assert not torch.allclose(fast, first)


@pytest.mark.slow
def test_shipped_pointpncnet_fast_path_equals_reference_path():
    """The whole network on the shipped weights: tiny, typical and capped clouds in one batch."""
    path = default_checkpoint("pointpncnet")
    if path is None:
        pytest.skip("no shipped PointPnCNet checkpoint")
    completer = load_completer("pointpncnet", path, device="cpu", batch_size=8)
    rng = np.random.default_rng(4)
    clouds = []
    for n in (5, 40, 300, 1500, 12, 800, 3, 200, 64):  # 9 clouds: a second, partial chunk of the batch
        pts = rng.uniform(-1, 1, (n, 3)) * [0.5, 0.2, 0.15]
        clouds.append(pts.astype(np.float32))
    fast = completer.complete(clouds)
    with on_path("reference", completer):
        ref = completer.complete(clouds)
    assert len(fast) == len(ref) == len(clouds)
    for a, b in zip(fast, ref):
        assert a.shape == b.shape
        np.testing.assert_allclose(a, b, rtol=0, atol=2e-5)


@pytest.mark.slow
def test_worker_threads_return_the_same_completions_in_order():
    from pcc_ros.errors import ConfigError
    from pcc_ros.models import create

    torch.manual_seed(0)
    single = create("pointpncnet", device="cpu", batch_size=4)
    threaded = create("pointpncnet", device="cpu", batch_size=4, workers=3)
    threaded.model.load_state_dict(single.model.state_dict())
    rng = np.random.default_rng(5)
    clouds = [(rng.uniform(-1, 1, (n, 3)) * [0.5, 0.2, 0.15]).astype(np.float32) for n in (30, 200, 7, 90, 400, 55, 12)]
    threads = torch.get_num_threads()
    expected = single.complete(clouds)
    got = threaded.complete(clouds)
    assert torch.get_num_threads() == threads  # restored after the call
    assert len(got) == len(expected)
    for a, b in zip(got, expected):  # same order, same values
        np.testing.assert_allclose(a, b, rtol=0, atol=2e-5)
    assert len(threaded.complete(clouds[:1])) == 1  # fewer instances than workers
    with pytest.raises(ConfigError, match="workers"):
        create("pointpncnet", device="cpu", workers=0)


def test_multi_thread_chunking_equals_reference(monkeypatch):
    """With several intra-op threads the chunks grow (fewer barriers); values stay the same."""
    monkeypatch.setattr(layers, "CHUNK_BYTES", 3 * 4 * (8 + 16 + 32 + 12))  # 3 rows
    monkeypatch.setattr(layers, "MULTI_THREAD_CHUNK_FACTOR", 4)  # 12-row chunks
    torch.manual_seed(0)
    enc = PCNEncoder([8, 16], [32, 12])
    points, segment = _packed(np.random.default_rng(6), [5, 0, 30, 2])
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        assert layers._rows_for([8, 16, 32, 12]) == 12
        with torch.no_grad():
            fast = enc(points, segment, 4)
            with on_path("reference", enc):
                ref = enc(points, segment, 4)
    finally:
        torch.set_num_threads(threads)
    torch.testing.assert_close(fast, ref, rtol=1e-5, atol=1e-6)


def test_octant_pairs_are_the_region_masks_memberships_grouped_by_instance_and_octant():
    """Points exactly on the planes and on the overlap bands' edges, empty clouds in the batch."""
    from pcc_ros.models.pointpncnet_network import octant_pairs, region_masks

    rng = np.random.default_rng(7)
    overlap = 0.005
    for _ in range(20):
        sizes = rng.integers(0, 200, rng.integers(1, 8))
        pts = (rng.uniform(-1, 1, (sizes.sum(), 3)) * rng.choice([1.0, 0.01], (sizes.sum(), 3))).astype(np.float32)
        for value in (0.0, overlap, -overlap):
            pts[rng.random(pts.shape) < 0.05] = np.float32(value)
        point_index, local = octant_pairs(pts, sizes, overlap)
        assert np.all(np.diff(local) >= 0)  # grouped: sorted by instance * 8 + octant
        rows, octants = np.nonzero(region_masks(pts, overlap))
        expected = np.repeat(np.arange(len(sizes)), sizes)[rows] * 8 + octants
        got, want = np.lexsort((point_index, local)), np.lexsort((rows, expected))
        np.testing.assert_array_equal(point_index[got], rows[want])
        np.testing.assert_array_equal(local[got], expected[want])


@pytest.mark.parametrize("rows", [1, 5, 12, 1000])
def test_segment_chunks_hold_whole_segments(rows):
    counts = torch.tensor([0, 3, 0, 7, 1, 0, 12, 2, 0])
    chunks = layers._segment_chunks(counts, rows)
    ends = set(np.cumsum(counts.numpy()).tolist())
    segment = np.repeat(np.arange(len(counts)), counts.numpy())
    assert chunks[0][0] == 0 and chunks[-1][1] == int(counts.sum())
    assert all(b == c for (_, b, _, _), (c, _, _, _) in itertools.pairwise(chunks))  # contiguous
    for a, b, lo, hi in chunks:
        assert b in ends and a < b  # cut only between segments
        assert b - a <= rows or (b - a) in counts.tolist()  # longer only when one segment alone is longer
        assert (lo, hi) == (segment[a], segment[b - 1] + 1)  # the chunk's segment range


def test_chunked_encoder_with_unsorted_segments_equals_reference(monkeypatch):
    """Unsorted segment ids take the two-pass path over all points; the value is the same."""
    monkeypatch.setattr(layers, "CHUNK_BYTES", 5 * 4 * (8 + 16 + 32 + 12))  # 5 rows
    torch.manual_seed(0)
    enc = PCNEncoder([8, 16], [32, 12])
    points, segment = _packed(np.random.default_rng(8), [4, 0, 13, 6])
    perm = torch.from_numpy(np.random.default_rng(9).permutation(len(points)))
    with torch.no_grad():
        fast = enc(points[perm], segment[perm], 5)
        with on_path("reference", enc):
            ref = enc(points, segment, 5)
    torch.testing.assert_close(fast, ref, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("backend", ["pointpncnet", "trapcc"])
def test_untrained_network_fast_path_equals_reference_path(backend):
    """The whole network (octant pairs, chunked encoders, folding) against the original path."""
    from pcc_ros.models import create

    torch.manual_seed(0)
    completer = create(backend, device="cpu", batch_size=4)
    rng = np.random.default_rng(10)
    clouds = [(rng.uniform(-1, 1, (n, 3)) * [0.5, 0.2, 0.15]).astype(np.float32) for n in (3, 70, 9, 400, 1100)]
    clouds[1][:10, 1] = 0.0  # on a plane: in two octants
    fast = completer.complete(clouds)
    with on_path("reference", completer):
        ref = completer.complete(clouds)
    for a, b in zip(fast, ref):
        np.testing.assert_allclose(a, b, rtol=0, atol=2e-5)


def test_reused_buffers_never_leak_into_returned_values():
    """The per-thread buffers are reused by the next call: what a call returned must not change."""
    torch.manual_seed(0)
    enc = PCNEncoder([8, 16], [32, 12])
    dec = FoldingDecoder(12, [16], num_coarse=5, grid_size=2, fold_widths=[10, 10], grid_scale=0.05)
    points, segment = _packed(np.random.default_rng(11), [6, 9])
    with torch.no_grad():
        code = enc(points, segment, 2)
        coarse, fine = dec(code)
        kept = [t.clone() for t in (code, coarse, fine)]
        enc(points * 3.0, segment, 2)  # bigger and different inputs through the same buffers
        dec(torch.randn(7, 12))
    for before, after in zip(kept, (code, coarse, fine)):
        assert torch.equal(before, after)


def test_workspace_keeps_small_buffers_and_drops_big_ones(monkeypatch):
    monkeypatch.setattr(inference, "WORKSPACE_KEEP_BYTES", 4096)
    ws, owner, like = inference.Workspace(), torch.nn.Linear(1, 1), torch.zeros(1)
    a = ws.get(owner, "x", 10, 20, like)  # 800 bytes: kept
    assert a.shape == (10, 20) and ws.get(owner, "x", 5, 20, like).data_ptr() == a.data_ptr()
    assert ws.get(owner, "y", 10, 20, like).data_ptr() != a.data_ptr()  # another slot, another buffer
    big = ws.get(owner, "x", 100, 20, like)  # 8000 bytes: fresh, not kept
    assert big.shape == (100, 20) and ws.get(owner, "x", 100, 20, like).data_ptr() != big.data_ptr()


def _pointpncnet_batch(seed: int, sizes: tuple[int, ...]):
    from pcc_ros.models import create
    from pcc_ros.models.pointpncnet import pack

    torch.manual_seed(seed)
    completer = create("pointpncnet", device="cpu", batch_size=len(sizes))
    rng = np.random.default_rng(seed)
    clouds = [(rng.uniform(-1, 1, (n, 3)) * [0.5, 0.2, 0.15]).astype(np.float32) for n in sizes]
    clouds[0][:] = [0.1, 0.05, 0.02]  # every point in one octant: the others absent
    return completer, pack(clouds, float(completer.config["region_overlap"]), pairs=True)


def _run(net, packed, compiled: bool, whole: bool = True):
    """The network's outputs on ``packed``: its compiled loops on or off, with them ``whole`` in
    one call or layer by layer (the ``compiled`` / ``compiled_layers`` / ``operators`` paths)."""
    out = torch.empty(packed.batch_size, net.num_global_points + 8 * net.num_local_points, 3)
    path = ("compiled" if whole else "compiled_layers") if compiled else "operators"
    with on_path(path, net), torch.inference_mode():
        y_global, y_local, present = net(packed.points, packed.segment, None, packed.batch_size, packed.pairs,
                                         out=out)
    return y_global.clone(), y_local.clone(), present.clone()


@pytest.mark.parametrize("chunk_bytes", [None, 3000])  # the default chunks, or many small ones
def test_pointpncnet_in_one_compiled_call_equals_the_layers_one_by_one(monkeypatch, _compiled_loops, chunk_bytes):
    """PointPnCNetNet's whole-network kernel (kernels.pointpncnet_infer) against the same layers
    run one by one: a cloud with one octant, tiny clouds (no octant with enough points) and
    bigger ones, in one chunk or in many."""
    from pcc_ros.models import kernels

    if chunk_bytes is not None:
        monkeypatch.setattr(layers, "CHUNK_BYTES", chunk_bytes)
    completer, packed = _pointpncnet_batch(21, (40, 2, 300, 1, 900, 60))
    calls = []
    infer = kernels.pointpncnet_infer
    monkeypatch.setattr(kernels, "pointpncnet_infer", lambda *args: calls.append(1) or infer(*args))
    whole = _run(completer.model, packed, _compiled_loops)
    assert len(calls) == (1 if _compiled_loops and inference.kernels_available() else 0)
    one_by_one = _run(completer.model, packed, _compiled_loops, whole=False)
    assert len(calls) <= 1  # layer by layer never calls it
    for a, b in zip(whole, one_by_one):
        torch.testing.assert_close(a, b, rtol=0, atol=2e-5)
    assert whole[2][0].sum() == 1 and not whole[2][1].any() and not whole[2][3].any()  # one octant, then none


def test_pointpncnet_compiled_call_grows_its_work_memory_and_keeps_it(monkeypatch, _compiled_loops):
    from pcc_ros.models.pointpncnet_network import SCRATCH

    monkeypatch.setattr(SCRATCH, "buffers", {})
    small_completer, small = _pointpncnet_batch(22, (30, 20))
    first = _run(small_completer.model, small, _compiled_loops)
    kept = SCRATCH.whole("network", np.float32)
    if not (_compiled_loops and inference.kernels_available()):  # the layers ran one by one: no such memory
        assert len(kept) == 0
        return
    assert len(kept) > 0
    completer, big = _pointpncnet_batch(22, (30, 20, 800, 20000, 700))  # one segment longer than any chunk
    _run(completer.model, big, True)
    grown = SCRATCH.whole("network", np.float32)
    assert len(grown) > len(kept)
    again = _run(small_completer.model, small, True)  # through the grown memory: the same values
    assert SCRATCH.whole("network", np.float32) is grown
    for a, b in zip(first, again):
        assert torch.equal(a, b)


def test_pointpncnet_with_unsorted_octant_pairs_runs_layer_by_layer(_compiled_loops):
    """The one-call kernel needs the pairs grouped by octant; otherwise the layers run (same values)."""
    completer, packed = _pointpncnet_batch(23, (50, 80, 20))
    expected = _run(completer.model, packed, _compiled_loops, whole=False)
    point_index, local = packed.pairs
    order = torch.from_numpy(np.random.default_rng(0).permutation(len(local)))
    packed.pairs = (point_index[order], local[order])
    got = _run(completer.model, packed, _compiled_loops)
    for a, b in zip(got, expected):
        torch.testing.assert_close(a, b, rtol=0, atol=2e-5)
