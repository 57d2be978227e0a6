"""ament_python / pip packaging for pcc_ros.

The same file serves colcon (``setup.py install --prefix ...``, scripts under
``lib/pcc_ros`` thanks to setup.cfg, data under ``share/pcc_ros``) and a plain
``pip install .`` into a virtualenv without ROS.
"""

import os
import subprocess
import sys
from glob import glob
from pathlib import Path

from setuptools import find_packages, setup
from setuptools.command.build_py import build_py

PACKAGE = "pcc_ros"


class BuildPyWithKernels(build_py):
    """``build_py``, then the shipped nodes' numba kernels compiled into the built package
    (``pcc_ros/_kernel_cache``, :mod:`pcc_ros.runtime.kernel_cache`): an installed node then
    starts in seconds instead of compiling for ~40 s, also from a read-only prefix. Needs the
    runtime libraries in the building Python (colcon, ``pip install --no-build-isolation``);
    where they are missing (pip's isolated build) or ``PCC_BUILD_KERNELS=0``, the nodes compile
    on their first start instead (into the user's cache). Never fails the build."""

    def run(self):
        super().run()
        if getattr(self, "editable_mode", False) or os.environ.get("PCC_BUILD_KERNELS", "1") == "0":
            return
        build_lib = Path(self.build_lib).resolve()
        target = build_lib / PACKAGE / "_kernel_cache"
        path = os.pathsep.join(filter(None, [str(build_lib), os.environ.get("PYTHONPATH")]))
        env = {**os.environ, "PYTHONPATH": path}
        print(f"compiling the pcc_ros kernels into {target} (PCC_BUILD_KERNELS=0 skips)", flush=True)
        out = subprocess.run([sys.executable, "-m", f"{PACKAGE}.runtime.kernel_cache", str(target),
                              str(Path(__file__).resolve().parent / "config")], env=env,
                             cwd=build_lib, capture_output=True, text=True)
        if out.returncode:
            print("pcc_ros kernels not compiled at build time (the nodes compile them on first start): "
                  + (out.stderr.strip().splitlines() or ["?"])[-1], flush=True)
        else:
            print(out.stdout.strip(), flush=True)


setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*", "benchmarks", "benchmarks.*"]),
    cmdclass={"build_py": BuildPyWithKernels},
    package_data={PACKAGE: ["weights/*.safetensors", "weights/*.json"]},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml") + glob("config/*.rviz") + glob("config/*.xml")),
        (f"share/{PACKAGE}/launch", glob("launch/*.launch.py")),
        (f"share/{PACKAGE}/weights", glob(f"{PACKAGE}/weights/*.safetensors") + glob(f"{PACKAGE}/weights/*.json")),
    ],
    # Runtime libraries. requirements.txt pins the exact versions the tests run against (torch:
    # the CPU wheel 2.13.0); here the range the code supports, so colcon/rosdep installs are not
    # over-constrained. torch: no private symbols or version-specific internals are used (the
    # compiled CPU loops reach BLAS through numba and SciPy, or MKL's public CBLAS); 2.3 is the
    # first release whose wheels run with numpy 2 and has every operator the layers call
    # (scatter_reduce amax, segment_reduce, inference_mode).
    install_requires=[
        "numpy>=1.26,<3",  # apt's Jazzy (Ubuntu 24.04) has numpy 1.26: a ROS workspace keeps it
        "torch>=2.3,<3",
        "rosbags>=0.10",
        "mcap>=1.1",
        "mcap-ros2-support>=0.5",
        'open3d-cpu>=0.18; platform_machine == "x86_64"',
        'open3d>=0.18; platform_machine != "x86_64"',
        "safetensors>=0.4",
        "tqdm>=4.60",
        "matplotlib>=3.6",
        "scipy>=1.10",
        "scikit-image>=0.22",
        "numba>=0.61",
        "pyyaml>=6",
        "pyarrow>=14",  # Argoverse 2 feather tables (imported only when one is read)
    ],
    # MKL (x86-64): the compiled loops' products through its public CBLAS (pcc_ros/models/blas.py),
    # which they use when it is installed; without it, SciPy's BLAS (0.8x the network's throughput).
    extras_require={"mkl": ['mkl>=2021; platform_machine == "x86_64"']},
    zip_safe=False,  # weights and configs are found through __file__
    maintainer="pcc_ros maintainers",
    maintainer_email="maintainers@pcc-ros.dev",
    description="LiDAR vehicle point cloud completion and detection filtering for ROS 2",
    license="Apache-2.0",
    tests_require=["pytest"],
    entry_points={
        "console_scripts": [
            "pcc = pcc_ros.cli.main:main",
            "completion_node = pcc_ros.nodes.completion_node:main",
            "detection_filter_node = pcc_ros.nodes.detection_filter_node:main",
            "completion_node_managed = pcc_ros.nodes.completion_node:main_managed",
            "detection_filter_node_managed = pcc_ros.nodes.detection_filter_node:main_managed",
        ],
    },
)
