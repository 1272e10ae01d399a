#!/usr/bin/env bash
# The README's test command: set everything up (idempotent) and run the whole suite.
# Extra arguments go to pytest (e.g. `scripts/test.sh -m "not slow"`).
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$ROOT/scripts/setup.sh"
cd "$ROOT"
export MUJOCO_GL="${MUJOCO_GL:-egl}"
# The whole suite takes ~20 min on 2 cores and about twice that beside a running twin (README,
# "Results"); a hang must end in a report, not in CI's own 90 min timeout.
# SIGINT makes pytest print where it was and the results so far.
LIMIT_S="${EQUIDIFF_TEST_LIMIT_S:-4500}"
set +e
timeout --signal=INT --kill-after=120 "$LIMIT_S" "$ROOT/.venv/bin/python" -m pytest "$@"
rc=$?
set -e
if [[ $rc -eq 124 ]]; then echo "the test suite ran past ${LIMIT_S} s (EQUIDIFF_TEST_LIMIT_S) and was stopped" >&2; exit 1; fi
# pytest exits 5 when it collected no test: that is a failure of the suite, say so.
if [[ $rc -eq 5 ]]; then echo "no tests were collected" >&2; exit 1; fi
exit $rc
