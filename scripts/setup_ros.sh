#!/usr/bin/env bash
# ROS 2 Jazzy for the project's venv (called by `make setup`; usage: scripts/setup_ros.sh [VENV]).
#
# * A ROS 2 Jazzy environment is sourced (ROS_DISTRO=jazzy): nothing to do, the system's
#   rclpy / vision_msgs / tf2_ros are used (check that they import, then stop).
# * Otherwise, from PyPI into VENV:
#   1. the pinned ros-jazzy-* wheels of requirements-ros.txt (rclpy + Fast DDS, the message
#      packages, the rosidl / ament_cmake tool chain and the generator packages the wheels use
#      but do not declare);
#   2. the wheels' exported *__rosidl_generator_pyExport.cmake files name the wheel builder's
#      Python and numpy include directories: they are pointed at this venv's;
#   3. a start-up hook (VENV/lib/pythonX.Y/site-packages/pcc_ros_ros_env.pth) adds VENV to
#      AMENT_PREFIX_PATH and defaults RMW_IMPLEMENTATION to rmw_fastrtps_cpp in every Python
#      process of the venv, so the nodes start from their entry points without sourcing
#      anything (LD_LIBRARY_PATH is set by the wheels' own ros_wheels_bootstrapper.pth);
#   4. vision_msgs and tf2_msgs (not among the wheels) are built from scripts/vision_msgs and
#      scripts/tf2_msgs with rosidl_generate_interfaces, their .msg files written from
#      pcc_ros/msg/typestore.py (BUILT_PACKAGES), and installed into VENV.
# Idempotent and cached: stamp files in VENV hold a hash of each step's inputs; a second run
# rebuilds nothing and prints one line.
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=${1:-.venv}
PY="$VENV/bin/python"
say() { echo "pcc_ros setup (ROS): $*"; }

if [ "${ROS_DISTRO:-}" = "jazzy" ]; then
  if ! "$PY" -c 'import rclpy, vision_msgs.msg, sensor_msgs.msg, tf2_msgs.msg' 2>/dev/null; then
    say "ROS_DISTRO=jazzy is sourced but rclpy / vision_msgs / tf2_msgs do not import in $PY." >&2
    say "  install them (apt-get install ros-jazzy-vision-msgs ros-jazzy-tf2-ros) and make the ROS Python packages visible" >&2
    say "  to the venv (PYTHONPATH from 'source /opt/ros/jazzy/setup.bash', same Python version)." >&2
    exit 1
  fi
  exit 0  # the sourced ROS 2 Jazzy install provides everything
fi
if [ -n "${ROS_DISTRO:-}" ]; then
  say "ROS_DISTRO=$ROS_DISTRO is sourced, but pcc_ros needs ROS 2 Jazzy: source Jazzy, or run" >&2
  say "  'make setup' in a shell without ROS to use the ROS 2 Jazzy wheels in the venv." >&2
  exit 1
fi

# ---------------------------------------------------------------- 1. wheels
wheel_key=$(sha256sum requirements-ros.txt | cut -d' ' -f1)
wheel_stamp="$VENV/.pcc_ros-ros-wheels"
if [ "$(cat "$wheel_stamp" 2>/dev/null)" != "$wheel_key" ]; then
  say "installing the pinned ROS 2 Jazzy wheels (requirements-ros.txt)"
  "$PY" -m pip install --disable-pip-version-check -q -r requirements-ros.txt
  echo "$wheel_key" > "$wheel_stamp"
fi

# ---------------------------------------------------- 2. + 3. include paths, start-up hook
"$PY" - "$VENV" <<'PYEOF'
"""Point the wheels' pyExport files at local include dirs; write the env start-up hook."""
import re
import sys
import sysconfig
from pathlib import Path

import numpy

venv = Path(sys.argv[1]).resolve()
py_include = sysconfig.get_paths()["include"]
np_include = numpy.get_include()
if not (Path(py_include) / "Python.h").is_file():
    sys.exit(f"pcc_ros setup (ROS): {py_include}/Python.h is missing: install the Python headers "
             "(apt-get install python3-dev), needed to build vision_msgs")


def local(entry: str) -> str:
    if re.search(r"numpy/(_core|core)/include$", entry):
        return np_include
    if re.search(r"/include/python3\.\d+$", entry):
        return py_include
    return entry


changed = 0
for path in sorted((venv / "share").glob("*/cmake/*__rosidl_generator_pyExport.cmake")):
    text = path.read_text()

    def fix(match: re.Match) -> str:
        dirs = ";".join(local(d) for d in match.group(2).split(";"))
        return f'{match.group(1)}"{dirs}"'

    new = re.sub(r'(INTERFACE_INCLUDE_DIRECTORIES )"([^"]*)"', fix, text)
    if new != text:
        path.write_text(new)
        changed += 1
if changed:
    print(f"pcc_ros setup (ROS): pointed {changed} *__rosidl_generator_pyExport.cmake files at "
          f"{py_include} and {np_include}")

# Runs at the start of every Python process of the venv (site.py executes .pth lines that
# begin with "import"). Sorted before the wheels' ros_wheels_bootstrapper.pth, which re-executes
# the interpreter with LD_LIBRARY_PATH set and keeps these variables.
hook = Path(sysconfig.get_paths()["purelib"]) / "pcc_ros_ros_env.pth"
line = (
    "import os, sys; "
    "_pcc_prefixes = [p for p in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep) if p]; "
    "os.environ['AMENT_PREFIX_PATH'] = os.pathsep.join(_pcc_prefixes + [sys.prefix] * (sys.prefix not in _pcc_prefixes)); "
    "os.environ.setdefault('RMW_IMPLEMENTATION', 'rmw_fastrtps_cpp')\n"
)
if not hook.exists() or hook.read_text() != line:
    hook.write_text(line)
PYEOF

# ------------------------------------------------------- 4. vision_msgs, tf2_msgs
# One package each, from scripts/PKG (package.xml, CMakeLists.txt) and the .msg texts of
# pcc_ros/msg/typestore.py (BUILT_PACKAGES), installed into VENV; each with its own stamp.
venv_abs=$(cd "$VENV" && pwd)
versions=$("$PY" -c 'import sys, numpy; print(sys.version.split()[0], numpy.__version__)')
build_messages() {
  local pkg=$1 build=build/$1 key stamp start
  rm -rf "$build/src" && mkdir -p "$build/src/msg"
  cp "scripts/$pkg/package.xml" "scripts/$pkg/CMakeLists.txt" "$build/src/"
  "$PY" - "$build/src/msg" "$pkg" <<'PYEOF'
import sys
from pathlib import Path

from pcc_ros.msg.typestore import BUILT_PACKAGES

for name, text in BUILT_PACKAGES[sys.argv[2]].items():
    (Path(sys.argv[1]) / f"{name.rsplit('/', 1)[1]}.msg").write_text(text.lstrip())
PYEOF
  key=$( (cat "$build"/src/package.xml "$build"/src/CMakeLists.txt "$build"/src/msg/*.msg; echo "$versions $wheel_key") \
    | sha256sum | cut -d' ' -f1)
  stamp="$VENV/.pcc_ros-$pkg"
  if [ "$(cat "$stamp" 2>/dev/null)" = "$key" ] && "$PY" -c "import $pkg.msg" 2>/dev/null; then
    return 0
  fi
  say "building $pkg (rosidl_generate_interfaces, about a minute)"
  rm -rf "$build/build" && mkdir -p "$build/build"
  start=$(date +%s)
  (
    cd "$build/build"
    export PATH="$venv_abs/bin:$PATH"
    cmake ../src -DCMAKE_PREFIX_PATH="$venv_abs" -DCMAKE_INSTALL_PREFIX="$venv_abs" -DCMAKE_BUILD_TYPE=Release \
      -DBUILD_TESTING=OFF -DPython3_EXECUTABLE="$venv_abs/bin/python" > cmake.log 2>&1 \
      || { tail -40 cmake.log >&2; say "cmake configure failed (log: $build/build/cmake.log)" >&2; exit 1; }
    make -j"$(nproc)" install > make.log 2>&1 \
      || { tail -40 make.log >&2; say "$pkg build failed (log: $build/build/make.log)" >&2; exit 1; }
  )
  "$PY" -c "import $pkg.msg" || { say "$pkg was built but does not import" >&2; exit 1; }
  echo "$key" > "$stamp"
  say "$pkg built and installed into $VENV in $(( $(date +%s) - start )) s"
  built=1
}
built=0
build_messages vision_msgs
build_messages tf2_msgs
if [ "$built" = 0 ]; then
  say "ROS 2 Jazzy wheels, vision_msgs and tf2_msgs up to date"
fi
