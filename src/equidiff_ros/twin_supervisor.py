"""The twin's supervisor and stack now live in ``equidiff_ros.twin``; these names are re-exported
for callers not yet moved there (``commands/bench_twin.py``)."""

from equidiff_ros.twin import (
    GatedPolicy,
    LiveExpert,
    LiveTwin,
    Supervisor,
    SupervisorError,
    TwinStack,
    run_policy_episode,
)

__all__ = [
    "GatedPolicy",
    "LiveExpert",
    "LiveTwin",
    "Supervisor",
    "SupervisorError",
    "TwinStack",
    "run_policy_episode",
]
