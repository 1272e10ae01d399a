#!/usr/bin/env bash
# One-time (and idempotent) set-up of a fresh Debian 12 / Ubuntu 24.04 machine:
# system packages, a Python 3.11 virtual environment in .venv with ROS 2 Jazzy rclpy
# (PyPI wheels), torch, escnn under numpy 2, franky + franky-sim, rosbags, mcap, rerun,
# open3d, pyrealsense2, and this package in editable mode. A second run with unchanged
# inputs returns in about a second (stamp file keyed on this script and setup.py).
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="${EQUIDIFF_VENV:-$ROOT/.venv}"
PY="${PYTHON:-python3.11}"
command -v "$PY" >/dev/null || PY=python3
STAMP="$VENV/.equidiff-setup-stamp"
KEY="$(cat "$ROOT/scripts/setup.sh" "$ROOT/scripts/build_lie_learn.py" "$ROOT/setup.py" | sha256sum | cut -c1-16)"

if [[ -f "$STAMP" && "$(cat "$STAMP")" == "$KEY" ]]; then
  exit 0
fi

# System libraries: gfortran builds py3nj; libusb for pyrealsense2/open3d; EGL/GL for
# headless MuJoCo rendering (MUJOCO_GL=egl).
APT_PKGS=(gfortran libusb-1.0-0 libegl1 libgl1 libegl-mesa0 libgl1-mesa-dri libglib2.0-0 libgomp1)
missing=()
for p in "${APT_PKGS[@]}"; do dpkg -s "$p" >/dev/null 2>&1 || missing+=("$p"); done
if ((${#missing[@]})); then
  SUDO=""; [[ $(id -u) -ne 0 ]] && SUDO="sudo"
  echo "[setup] apt-get install ${missing[*]}"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "${missing[@]}" >/dev/null
fi

[[ -x "$VENV/bin/python" ]] || "$PY" -m venv "$VENV"
PIP=("$VENV/bin/python" -m pip install -q --disable-pip-version-check)
echo "[setup] python packages into $VENV"
# colcon-core wants setuptools<80, torch 2.13 wants >=77.0.3.
"${PIP[@]}" -U pip "setuptools>=77.0.3,<80" wheel
# torch first and pinned: the CPU build on machines without a GPU (a plain `torch`
# would pull a multi-GB CUDA build).
"${PIP[@]}" "torch==2.13.0" "numpy>=2" scipy cython requests
WHEEL="$("$VENV/bin/python" "$ROOT/scripts/build_lie_learn.py" "$VENV/wheel-cache")"
"${PIP[@]}" "$WHEEL"
"${PIP[@]}" py3nj
"${PIP[@]}" -e "$ROOT[ros,viz,twin,robot,realsense,spacemouse,open3d,calib,export,dev]" "torch==2.13.0"
"$VENV/bin/python" -m pip check
echo "$KEY" > "$STAMP"
echo "[setup] done: $VENV"
