#!/usr/bin/env bash
# Install the Debian/Ubuntu packages a fresh machine lacks, and only those.
#   libusb-1.0-0 : open3d's Python module links against libusb-1.0.so.0
#   libgomp1     : OpenMP runtime used by open3d and torch
#   python3-venv : `python3 -m venv` on Debian/Ubuntu system Pythons
# Idempotent: prints nothing and installs nothing when everything is present.
set -euo pipefail

missing=()
ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0' || missing+=(libusb-1.0-0)
ldconfig -p 2>/dev/null | grep -q 'libgomp.so.1' || missing+=(libgomp1)
python3 -c 'import venv, ensurepip' 2>/dev/null || missing+=(python3-venv)

[ ${#missing[@]} -eq 0 ] && exit 0

echo "pcc_ros setup: installing system packages: ${missing[*]} (needed by open3d / torch / venv)"
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
