"""`equidiff bench control`: tracking, safety and latency of the franka node on franky-sim.

Starts franky-sim and the franka node (real franky client, real rclpy, separate processes),
then drives the node from this process exactly as the policy would, over /franka/command_chunk:

1. **track**: a 5 cm circle at ``--speed`` m/s, as 16-pose chunks (dt 0.2 s) published every
   0.2 s and stamped ``--obs-latency`` in the past (like a policy's observation); RMS distance
   of the measured TCP from the circle after ``--settle`` s (``tracking_rms_mm``) and how often
   the TCP ran backwards along it (``velocity_reversals``). Baseline in the same run: the
   commanded targets (``/franka/executed_target``) against the same circle. Without time:
   ``path_rms_mm``, the TCP's distance from the circle as a curve (off the path, not late on
   it), and ``arc_travelled_mm``, how far along it went.
2. **hold**: commands stop; the watchdog holds; largest drift over the next 2 s (``hold_drift_mm``).
3. **workspace**: chunks that keep asking to go up and out, past the workspace box; largest distance
   of the measured TCP outside the (unshrunk) box (``max_outside_workspace_mm``).
4. **nan**: a chunk with a NaN pose; the node's ``nan_rejected`` diagnostics count and whether
   it kept publishing its state.
5. **latency** (unless ``--no-policy``): the policy node with ``--policy-checkpoint`` (default: an
   untrained export of the compact preset, since latency does not depend on the weights) on
   synthetic 5 Hz voxel grids; observation stamp -> chunk received here (``obs_to_cmd_p50_ms``,
   ``obs_to_cmd_p95_ms``), with the bare ``InferencePolicy.predict`` time measured in this
   process before anything else starts as the baseline (``baseline_bare_predict_p50_ms``).

**Standstill at chunk boundaries** (docs/chunking.md): ``track_standstill_*`` is how long the
commanded TCP (/franka/executed_target) stands still at each chunk switch of the circle (target
0: franka_node continues the motion through a switch); ``policy_standstill_*`` is the same for
the policy node with its default parameters (``latency_s`` auto), read off its chunks' timing
(each switch: how long after the previous chunk's last step the next chunk arrived), with
``baseline_whole_chunks_policy_standstill_*`` for ``latency_s:=-1`` (whole chunks, the former
default) in the same run.

Prints one JSON line.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from equidiff_core.runtime.machine import PRECISIONS

# approach: bench safety drives the arm with it and imports it from here
from equidiff_ros.benches.control import run_control_bench


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--speed", type=float, default=0.06, help="speed along the circle, m/s (default 0.06)")
    parser.add_argument("--radius", type=float, default=0.05, help="circle radius, m (default 0.05)")
    parser.add_argument("--duration", type=float, default=5.0, help="seconds of circle streaming (default 5)")
    parser.add_argument("--settle", type=float, default=1.0, help="seconds ignored at the start of the circle")
    parser.add_argument(
        "--obs-latency",
        type=float,
        default=0.1,
        help="chunks are stamped this long before they are sent (default 0.1 s)",
    )
    parser.add_argument(
        "--interpolation",
        choices=["linear", "cubic"],
        default=None,
        help="override control.yaml's scheduler interpolation",
    )
    parser.add_argument(
        "--policy-checkpoint",
        type=Path,
        default=None,
        help="exported policy for the latency phase (default: untrained compact export)",
    )
    parser.add_argument("--policy-preset", default="compact", help="preset of the untrained export (default compact)")
    parser.add_argument("--precision", choices=PRECISIONS, default="auto")
    parser.add_argument("--latency-duration", type=float, default=15.0, help="seconds of policy latency measurement")
    parser.add_argument("--no-policy", action="store_true", help="skip the latency phase")
    parser.add_argument("--domain-id", type=int, default=None, help="ROS_DOMAIN_ID (default: a random private one)")


def run(args: argparse.Namespace) -> int:
    return run_control_bench(args)
