"""Compile the shipped nodes' numba kernels into a cache folder (``setup.py`` runs it at build time).

``python -m pcc_ros.runtime.kernel_cache DIR [CONFIG_DIR]`` builds each node's pipeline as the node builds it
from its shipped parameter file (on the CPU) and runs one small frame through it, so every
kernel a node compiles on its first start is compiled here instead, into ``DIR``
(:data:`pcc_ros.jit.CACHE_ENV` points numba there; set before anything imports the kernels).
The build puts ``DIR`` inside the package (``pcc_ros/_kernel_cache``), which the nodes seed their
writable cache from (:mod:`pcc_ros.jit`): a fresh or read-only install starts in seconds, not
the ~40 s the compilation takes on a 2-core machine.
"""

from __future__ import annotations

import os
import sys
import time


def compile_kernels(config_dir: str | None = None) -> dict[str, float]:
    """Build each node's pipeline (shipped parameters, CPU; the files of ``config_dir``, default
    the installed or checked-out ``config/``) and run one synthetic frame; returns the seconds
    each node took."""
    import numpy as np

    from pcc_ros.pipeline.config import CONFIG_FILES, load_parameters, pipeline_config
    from pcc_ros.pipeline.core import Pipeline
    from pcc_ros.runtime.node import MODES, output_names, pipeline_stages
    from pcc_ros.types import Boxes

    rng = np.random.default_rng(0)
    car = rng.normal(size=(400, 3)) * [1.2, 0.5, 0.4] + [12.0, 0.0, -0.9]
    ground = np.c_[rng.uniform(-30, 30, (2000, 2)), np.full(2000, -1.7)]
    points = np.r_[car, ground].astype(np.float32)
    boxes = Boxes([[12.0, 0.0, -0.9]], [[4.0, 1.7, 1.5]], [0.0], ["Car"], [0.9], ["1"])
    seconds = {}
    for mode in MODES:
        tic = time.perf_counter()
        path = None if config_dir is None else os.path.join(config_dir, CONFIG_FILES[mode])
        values = load_parameters(path, with_filter=mode == "filter", device="cpu")
        pipeline = Pipeline(pipeline_config(values), **pipeline_stages(output_names(mode)))
        pipeline.process(points, boxes)
        seconds[mode] = time.perf_counter() - tic
    return seconds


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) not in (1, 2):
        print("usage: python -m pcc_ros.runtime.kernel_cache DIR [CONFIG_DIR]", file=sys.stderr)
        return 2
    from pcc_ros.jit import CACHE_ENV

    os.environ[CACHE_ENV] = argv[0]
    seconds = compile_kernels(argv[1] if len(argv) == 2 else None)
    print("pcc_ros kernels compiled into " + argv[0] + ": "
          + ", ".join(f"{mode} node {s:.1f} s" for mode, s in seconds.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
