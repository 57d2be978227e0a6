#!/usr/bin/env bash
# Install the Debian/Ubuntu packages a fresh machine lacks, and only those.
#   libusb-1.0-0 : open3d's Python module links against libusb-1.0.so.0
#   libgomp1     : OpenMP runtime used by open3d and torch
#   python3-venv : `python3 -m venv` on Debian/Ubuntu system Pythons
# and, unless a ROS 2 Jazzy environment is sourced (then its packages are used), what
# scripts/setup_ros.sh needs to build vision_msgs against the ROS 2 Jazzy wheels:
#   cmake, g++, make : rosidl_generate_interfaces (C / C++ type support, Python extension)
#   python3-dev      : Python.h, when the interpreter's headers are not installed
# Idempotent: prints nothing and installs nothing when everything is present.
set -euo pipefail

missing=()
ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0' || missing+=(libusb-1.0-0)
ldconfig -p 2>/dev/null | grep -q 'libgomp.so.1' || missing+=(libgomp1)
python3 -c 'import venv, ensurepip' 2>/dev/null || missing+=(python3-venv)
if [ "${ROS_DISTRO:-}" != "jazzy" ]; then
  command -v cmake >/dev/null 2>&1 || missing+=(cmake)
  command -v g++ >/dev/null 2>&1 || missing+=(g++)
  command -v make >/dev/null 2>&1 || missing+=(make)
  python3 -c 'import os, sysconfig, sys; sys.exit(not os.path.isfile(os.path.join(sysconfig.get_paths()["include"], "Python.h")))' \
    2>/dev/null || missing+=(python3-dev)
fi

[ ${#missing[@]} -eq 0 ] && exit 0

echo "pcc_ros setup: installing system packages: ${missing[*]} (needed by open3d / torch / venv / the vision_msgs build)"
if [ "$(id -u)" -eq 0 ]; then
  SUDO=""
elif command -v sudo >/dev/null 2>&1; then
  SUDO="sudo"
else
  echo "pcc_ros setup: cannot install ${missing[*]}: not root and no sudo." >&2
  echo "  Ask an administrator to run: apt-get install -y ${missing[*]}" >&2
  exit 1
fi
if ! command -v apt-get >/dev/null 2>&1; then
  echo "pcc_ros setup: no apt-get here; install the equivalents of: ${missing[*]}" >&2
  exit 1
fi
export DEBIAN_FRONTEND=noninteractive
$SUDO apt-get update -qq
$SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}"
