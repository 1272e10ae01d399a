#!/usr/bin/env bash
# The GPU check in one command: inference, training and DDP on CUDA, one JSON file.
#
#   bash scripts/gpu_check.sh                       # on the GPU machine: <= 8 min, writes
#                                                   # docs/results/gpu_check.json (and $OUT/...)
#   bash scripts/gpu_check.sh --device cpu --tiny   # the rehearsal on a CPU: same code paths, tiny sizes
#
# The GPU machine's own python3 (3.12, torch with CUDA, numpy, scipy...) runs it. What that Python
# lacks (escnn and its lie_learn, pymanopt, autograd, py3nj; diffusers) cannot come from a
# registry there: scripts/gpu_prepare.sh builds the wheels here into .gpu_carry/wheels, with the
# packed training episodes in .gpu_carry/packed, and the device call carries .gpu_carry.
# Options after the script name go to `scripts/gpu_check.py run` (--budget-s, --json, --work, ...).
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
PY="${PYTHON:-python3}"
CARRY="$ROOT/.gpu_carry"
SITE="${GPU_CHECK_SITE:-/tmp/equidiff_gpu_site}"

if ! "$PY" -c "import torch" 2>/dev/null; then
  echo "gpu_check: $PY has no torch; torch cannot be carried (too large): nothing to check" >&2
  exit 2
fi
if ! "$PY" -c "import escnn, diffusers" 2>/dev/null; then
  if [[ ! -d "$CARRY/wheels/required" ]]; then
    echo "gpu_check: $PY lacks escnn/diffusers and $CARRY/wheels is missing: run scripts/gpu_prepare.sh and carry .gpu_carry" >&2
    exit 2
  fi
  rm -rf "$SITE"
  # the device machine reaches no registry: the carried wheels only, as they are (no dependency resolution)
  "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target "$SITE" "$CARRY"/wheels/required/*.whl
  # py3nj (Fortran, with its libgfortran) only speeds up escnn's SO(3) Clebsch-Gordan coefficients:
  # escnn falls back to a numerical method without it, so a platform that refuses it costs nothing
  "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target "$SITE" "$CARRY"/wheels/optional/*.whl \
    || echo "gpu_check: py3nj not installed; escnn computes Clebsch-Gordan coefficients numerically" >&2
  export PYTHONPATH="$SITE${PYTHONPATH:+:$PYTHONPATH}"
fi
export PYTHONPATH="$ROOT/src:${PYTHONPATH:-}"
export PYTHONUNBUFFERED=1
cd "$ROOT"
exec "$PY" "$ROOT/scripts/gpu_check.py" run "$@"
