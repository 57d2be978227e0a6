"""ament_python / pip packaging for pcc_ros.

The same file serves colcon (``setup.py install --prefix ...``, scripts under
``lib/pcc_ros`` thanks to setup.cfg, data under ``share/pcc_ros``) and a plain
``pip install .`` into a virtualenv without ROS.
"""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = "pcc_ros"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*", "benchmarks", "benchmarks.*"]),
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
    # compiled CPU loops reach BLAS through numba and SciPy); 2.3 is the first release whose
    # wheels run with numpy 2 and has every operator the layers call (scatter_reduce amax,
    # segment_reduce, inference_mode).
    install_requires=[
        "numpy>=1.24",
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
        ],
    },
)
