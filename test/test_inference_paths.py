"""Inference settings belong to a completer: its path (compiled loops, torch operators, the
original path), precision and device, chosen by capability where not named, and several
completers with different settings side by side in one process (threads included).

Values only; speed is ``pcc bench complete``'s.
"""

from __future__ import annotations

import threading

import numpy as np
import pytest
import torch

from pcc_ros.errors import ConfigError
from pcc_ros.models import create, inference
from pcc_ros.models.inference import resolve_path

CUDA = torch.cuda.is_available()
NO_CUDA = "no CUDA device here: the device=cuda and half_precision-on-GPU paths are not run"


def _clouds(seed: int, sizes=(3, 70, 9, 400, 1100, 40)) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    clouds = [(rng.uniform(-1, 1, (n, 3)) * [0.5, 0.2, 0.15]).astype(np.float32) for n in sizes]
    clouds[1][:10, 1] = 0.0  # on a plane: in two octants
    return clouds


def _completers(settings: list[dict], backend: str = "pointpncnet") -> list:
    """One completer per settings dict, all with the same (untrained, seeded) weights."""
    torch.manual_seed(0)
    first = create(backend, batch_size=4, **settings[0])
    state = {k: v.float() for k, v in first.model.state_dict().items()}
    out = [first]
    for s in settings[1:]:
        c = create(backend, batch_size=4, **s)
        c.model.load_state_dict(state)
        out.append(c)
    return out


def test_resolve_path_by_capability_device_and_precision():
    assert resolve_path("auto", "cpu", False, available=True) == "compiled"
    assert resolve_path("auto", "cpu", False, available=False) == "operators"
    assert resolve_path("auto", "cpu", True, available=True) == "operators"  # bfloat16: torch operators
    assert resolve_path("auto", "cuda", False, available=True) == "operators"
    for path in ("operators", "reference"):
        assert resolve_path(path, "cuda", True, available=False) == path
    with pytest.raises(ConfigError, match="numba and SciPy's BLAS"):
        resolve_path("compiled", "cpu", False, available=False)
    with pytest.raises(ConfigError, match="CPU in float32 only"):
        resolve_path("compiled_layers", "cuda", False, available=True)
    with pytest.raises(ConfigError, match="CPU in float32 only"):
        resolve_path("compiled", "cpu", True, available=True)
    with pytest.raises(ConfigError, match="inference_path must be one of"):
        resolve_path("fastest", "cpu", False)


@pytest.mark.parametrize("backend", ["pointpncnet", "trapcc"])
def test_fast_path_present_or_absent_gives_the_same_completions(monkeypatch, backend):
    """``auto`` takes the compiled loops where they load and torch operators where they do not
    (the capability check says no): equal outputs, both equal to the original path."""
    clouds = _clouds(1)
    with_kernels, reference = _completers([{"device": "cpu"}, {"device": "cpu", "inference_path": "reference"}],
                                          backend)
    assert with_kernels.inference_path == ("compiled" if inference.kernels_available() else "operators")
    monkeypatch.setattr(inference, "kernels_available", lambda: False)
    (without,) = _completers([{"device": "cpu"}], backend)
    assert without.inference_path == "operators"
    with pytest.raises(ConfigError, match="numba"):
        create(backend, device="cpu", inference_path="compiled")
    a, b, ref = (c.complete(clouds) for c in (with_kernels, without, reference))
    for x, y, r in zip(a, b, ref):
        np.testing.assert_allclose(x, y, rtol=0, atol=2e-5)
        np.testing.assert_allclose(x, r, rtol=0, atol=2e-5)


def test_two_completers_with_different_settings_side_by_side_in_threads():
    """Completers on different paths and precisions in one process, called from several threads
    at once (one of them with worker threads of its own), each return what it returns alone."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # the worker completer sets 1 while it runs: the same chunks for all
    try:
        settings = [{"device": "cpu", "workers": 2},  # auto: the compiled loops where they load
                    {"device": "cpu", "inference_path": "operators", "half_precision": True},  # bfloat16
                    {"device": "cpu", "inference_path": "reference"}]
        completers = _completers(settings)
        assert [c.inference_path for c in completers][1:] == ["operators", "reference"]
        inputs = [_clouds(10 + i) for i in range(len(completers))]
        alone = [c.complete(x) for c, x in zip(completers, inputs)]
        got: dict[int, list] = {}
        errors: list[BaseException] = []

        def run(i: int) -> None:
            try:
                got[i] = [completers[i].complete(inputs[i]) for _ in range(3)]
            except BaseException as exc:  # reported below, not lost in the thread
                errors.append(exc)

        workers = [threading.Thread(target=run, args=(i,)) for i in range(len(completers))]
        for w in workers:
            w.start()
        for w in workers:
            w.join()
    finally:
        torch.set_num_threads(threads)
    assert not errors, errors
    for i, expected in enumerate(alone):
        for repeat in got[i]:
            for a, b in zip(repeat, expected):
                np.testing.assert_array_equal(a, b)
    # the settings really differ: bfloat16 is not float32's completion
    assert max(float(np.abs(a - b).max()) for a, b in zip(alone[1], completers[0].complete(inputs[1]))) > 1e-4


def test_inference_path_changes_between_calls_on_one_completer():
    (completer,) = _completers([{"device": "cpu"}])
    clouds = _clouds(2)
    first = completer.complete(clouds)
    completer.inference_path = "reference"
    assert completer.inference_path == "reference"
    assert {m.inference_path for m in completer.model.modules() if hasattr(m, "inference_path")} == {"reference"}
    for a, b in zip(completer.complete(clouds), first):
        np.testing.assert_allclose(a, b, rtol=0, atol=2e-5)
    with pytest.raises(ConfigError, match="inference_path"):
        completer.inference_path = "bogus"
    assert completer.inference_path == "reference"  # a refused value changes nothing


def test_bfloat16_on_cpu_stays_close_to_float32():
    full, half = _completers([{"device": "cpu"}, {"device": "cpu", "half_precision": True}])
    assert half.inference_path == "operators"
    for a, b in zip(full.complete(_clouds(3)), half.complete(_clouds(3))):
        assert a.dtype == b.dtype == np.float32
        np.testing.assert_allclose(a, b, rtol=0, atol=0.05)


@pytest.mark.skipif(not CUDA, reason=NO_CUDA)
@pytest.mark.parametrize("half_precision", [False, True])
def test_cuda_completions_match_the_cpu(half_precision):
    """``device: cuda`` (float32, and float16 with ``half_precision``) against the CPU's float32."""
    cpu, gpu = _completers([{"device": "cpu"}, {"device": "cuda", "half_precision": half_precision}])
    assert gpu.inference_path == "operators"
    clouds = _clouds(4)
    for a, b in zip(cpu.complete(clouds), gpu.complete(clouds)):
        assert b.dtype == np.float32
        np.testing.assert_allclose(a, b, rtol=0, atol=0.05 if half_precision else 1e-4)


@pytest.mark.skipif(not CUDA, reason=NO_CUDA)
@pytest.mark.parametrize("backend", ["trapcc", "aml"])
@pytest.mark.parametrize("half_precision", [False, True])
def test_cuda_completes_the_other_shipped_backends_like_the_cpu(backend, half_precision):
    """TraPCC and AML (shipped weights) on ``device: cuda``: each completion within a small
    Chamfer-L1 of the CPU's (order-free: AML samples its decoded surface)."""
    from pcc_ros.metrics.chamfer import chamfer_batch
    from pcc_ros.models import load_completer

    clouds = [c for c in _clouds(6) if len(c) >= 9]
    cpu = load_completer(backend, device="cpu", batch_size=4)
    gpu = load_completer(backend, device="cuda", batch_size=4, half_precision=half_precision)
    torch.manual_seed(0)
    want = cpu.complete(clouds)
    torch.manual_seed(0)
    got = gpu.complete(clouds)
    assert all(g.dtype == np.float32 and len(g) == len(w) for g, w in zip(got, want))
    # AML's surface is a marching-cubes level set of a decoded grid: float32 on another device moves
    # it by about a millimetre (in a frame where the car is ~1 long)
    assert chamfer_batch(got, want)["cd_l1"].max() < (0.02 if half_precision else 5e-3)


@pytest.mark.skipif(not CUDA, reason=NO_CUDA)
def test_cuda_refuses_the_compiled_path_and_runs_beside_a_cpu_completer():
    with pytest.raises(ConfigError, match="CPU in float32 only"):
        create("pointpncnet", device="cuda", inference_path="compiled")
    cpu, gpu = _completers([{"device": "cpu"}, {"device": "cuda"}])
    clouds = _clouds(5)
    expected = cpu.complete(clouds), gpu.complete(clouds)
    results: dict[str, list] = {}
    workers = [threading.Thread(target=lambda n=n, c=c: results.__setitem__(n, c.complete(clouds)))
               for n, c in (("cpu", cpu), ("gpu", gpu))]
    for w in workers:
        w.start()
    for w in workers:
        w.join()
    for got, want in zip((results["cpu"], results["gpu"]), expected):
        for a, b in zip(got, want):
            np.testing.assert_allclose(a, b, rtol=0, atol=1e-6)


@pytest.mark.parametrize("given, expected", [(None, "1 1"), ("3", "3 ")])
def test_import_pcc_ros_loads_blas_single_threaded_unless_told(given, expected):
    """OpenBLAS reads OPENBLAS_NUM_THREADS once, when it loads: after ``import pcc_ros`` numpy's
    and SciPy's BLAS (the compiled loops' products) start no helper threads; a count the user
    gave is kept."""
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k not in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS")}
    if given is not None:
        env["OPENBLAS_NUM_THREADS"] = given
    code = ("import os, pcc_ros, numpy, scipy.linalg.cython_blas; "
            "one = len(os.listdir('/proc/self/task')) == 1 if os.path.isdir('/proc/self/task') else 1; "
            "print(os.environ['OPENBLAS_NUM_THREADS'], int(one) if os.environ['OPENBLAS_NUM_THREADS'] == '1' else '')")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env)
    assert out.stdout.strip() == expected.strip(), out.stderr
