"""``python -m equidiff_core.training.process SPEC_JSON``: one training run in a process of its own, for the
benches that train several policies side by side (``benches.training_runs``).

It parses nothing but a ``TrainingSpec``'s JSON and then runs and reports exactly as ``equidiff train``
with the same settings does: progress on stderr, the summary as one JSON line on stdout, an error as
``equidiff train: <message>`` with the command's exit status.
"""

from __future__ import annotations

import json
import sys

from equidiff_core.runtime.jobs import error_message, progress_lines
from equidiff_core.runtime.machine import default_threads_to_idle_cores


def main(argv: list[str]) -> int:
    # a process entry point: its stdout and stderr are the run's train.log, whose tail the bench that started
    # it reports on a failure
    if len(argv) != 1:
        print("usage: python -m equidiff_core.training.process SPEC_JSON (a TrainingSpec.to_json)", file=sys.stderr)
        return 2
    default_threads_to_idle_cores()  # before torch is imported, as the CLI does
    from equidiff_core.training.job import TrainingSpec, run_training

    spec = TrainingSpec.from_json(argv[0])
    try:
        with progress_lines("stderr", "equidiff train: "):
            summary = run_training(spec)
    except Exception as err:
        known = error_message(err)
        if known is None:
            raise
        print(f"equidiff train: {known[0]}", file=sys.stderr)
        return known[1]
    if summary is not None:
        print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
