#!/usr/bin/env bash
# The README's main-job command: set everything up (idempotent), then run the whole stack
# end to end in the digital twin (franky-sim + simulated cameras + all nodes).
# Extra arguments go to `equidiff twin run` (e.g. `--episodes 5`).
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$ROOT/scripts/setup.sh"
cd "$ROOT"
export MUJOCO_GL="${MUJOCO_GL:-egl}"
exec "$ROOT/.venv/bin/equidiff" twin run "$@"
