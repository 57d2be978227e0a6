"""The compiled kernels' disk cache (pcc_ros.jit): relocatable, seeded from the shipped cache.

What makes a fresh or read-only install start in seconds: a cache compiled in one place (the
build's ``pcc_ros/_kernel_cache``) is copied into a process's empty writable cache and loaded
from there, nothing compiled.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def test_a_cache_compiled_elsewhere_seeds_an_empty_one_and_loads_without_compiling(tmp_path):
    """Kernels in one cache folder (the user's cache of this test run, compiled once; the build
    writes ``pcc_ros/_kernel_cache`` the same way) are found by a process whose own cache is empty
    and elsewhere (a fresh XDG_CACHE_HOME), once that folder is its shipped cache: every filter
    kernel loads, none compiles, and the cache is laid out relative to the package."""
    user = tmp_path / "xdg"
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    for key in ("NUMBA_CACHE_DIR", "PCC_KERNEL_CACHE"):
        env.pop(key, None)
    compile_ = ("import pcc_ros.jit as jit; from pcc_ros.pipeline.evidence import warm_up; warm_up(); "
                "print(jit.cache_root())")
    out = subprocess.run([sys.executable, "-c", compile_], env=env, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    shipped = Path(out.stdout.strip().splitlines()[-1])
    entries = sorted(p.relative_to(shipped).parts[:3] for p in shipped.rglob("*.nbi"))
    assert ("pcc_ros", "pipeline") in {e[:2] for e in entries} and {e[0] for e in entries} == {"pcc_ros"}

    load = (
        "import json, pathlib, pcc_ros.jit as jit; jit.SHIPPED_CACHE = pathlib.Path(" + repr(str(shipped)) + "); "
        "from pcc_ros.pipeline import evidence_kernels as k; from pcc_ros.pipeline.evidence import warm_up; "
        "warm_up(); kernels = [k.counting_sort, k.ray_keys, k.ray_counts, k.ground_cells, k.ground_quantiles, "
        "k.expected_counts]; print(json.dumps({'root': str(jit.cache_root()), "
        "'misses': sum(sum(f.stats.cache_misses.values()) for f in kernels), "
        "'hits': sum(sum(f.stats.cache_hits.values()) for f in kernels)}))"
    )
    out = subprocess.run([sys.executable, "-c", load], env={**env, "XDG_CACHE_HOME": str(user)},
                         capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    got = json.loads(out.stdout.strip().splitlines()[-1])
    assert Path(got["root"]) == user / "pcc_ros" / "kernels"
    assert got["misses"] == 0 and got["hits"] >= 6, got
    assert sorted(p.relative_to(got["root"]).parts[:3] for p in Path(got["root"]).rglob("*.nbi")) == entries
