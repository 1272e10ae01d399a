"""``equidiff bench safety``: the fault campaign against franky-sim through franka_node, ROS-free; the ROS
side comes in as a ``Probe`` (``equidiff_ros.benches.safety_probe.SafetyProbe``).

* ``driver``: the campaign (set-up, one fault at a time, the JSON line); ``campaign``: its state and moves.
* ``chunk_faults``, ``stop_faults``, ``node_faults``: the faults, each with what surviving it means.
* ``report``: the summary across the campaign (excursion, auto-resumes, episodes lost).
"""

from equidiff_core.benches.fault_campaign.campaign import Probe
from equidiff_core.benches.fault_campaign.driver import FAULTS, run_bench, run_campaign

__all__ = ["FAULTS", "Probe", "run_bench", "run_campaign"]
