"""`equidiff bench safety`: a fault campaign against franky-sim through franka_node (issues 16 and 27).

    equidiff bench safety                          # all fourteen faults
    equidiff bench safety --faults nan,out_of_box,user_stop,franka_node_killed
    equidiff bench safety --faults out_of_box --box-margin-mm 0   # the raw overshoot the margin is set from

Starts the twin's franky-sim (its scene, scene seed chosen so no object lies near the arm's
approaches; the robot faults are injected at the libfranka protocol level, so the real franky
client raises the real exceptions: ``robots.franky.faults``), franka_node (real franky client,
real rclpy, separate processes, the lab's defaults: it holds at start until acknowledged, which
the bench does as the operator) and recorder_node, then drives franka_node over
/franka/command_chunk the way the policy does and injects one fault at a time, each checked
for what "survived" means for it:

* ``nan``, ``jump``, ``stale_chunk``, ``out_of_cone``: a chunk with a NaN pose / a first step
  15 cm from the arm / stamped 2 s ago / tilted 60 deg from tool-down. Survived: counted as
  rejected in franka_node's /diagnostics, the node alive, the arm still (< ``--still-mm``).
* ``out_of_box``: at the speed limit (chunks asking for 0.3 m/s, the filter allows 0.25) into
  the floor, the -y and +x walls and the corner of the -y wall and the floor, each from a start
  9-21 cm away. Reports each
  approach's ``overshoot_mm`` (the measured TCP past the plane commands stop at: the box shrunk
  by control.yaml's ``safety.box_margin_m``), its ``outside_mm`` (past the safety box itself,
  lab.yaml), ``travel_mm`` and ``speed_limited`` (franka_node's speed limit cut the command). Survived: 0 mm outside. With ``--box-margin-mm 0`` the
  overshoot is the raw one the margin is set from (docs/control.md).
* ``user_stop``: pressed while the arm follows a policy's chunks (the sender goes on throughout),
  held 2 s, an acknowledgement tried while pressed, released, then acknowledged. ``reflex``:
  a collision reflex mid-motion, then acknowledged. ``connection_lost``: the robot stops
  answering for 1.5 s (libfranka's 1 s receive timeout kills its connection), then
  acknowledged (franka_node connects again). ``divergence``: the sender yaws the hand on and on
  until joint 7 runs into its position limit (franka_node's divergence stop), then acknowledged.
  Survived, each: franka_node (the same process) held (/franka/status ``awaiting_ack`` with the
  fault's reason), the arm still and every chunk refused until the acknowledgement (an
  acknowledgement while the user stop is pressed is refused), and after it the arm follows the
  chunks again.
* ``camera_stall``: the twin's cameras (three camera_nodes, backend twin, rendering the sim's
  own state) -> voxel_node -> policy_node (``--policy``: ``shipped``, the twin's trained
  checkpoint, the default; or ``standin``, an untrained tiny one that starts in seconds) drive
  the arm; one camera stalls for 5 s (its reads time out), so voxel_node's sets stop.
  ``policy_chunks_accepted`` says how many of the policy's chunks franka_node executed.
  Survived: no chunk answers an observation taken during the stall, the arm held, chunks again
  once the camera is back.
* ``policy_node_killed``: that policy_node is SIGKILLed. Survived: the arm held (watchdog).
* ``recorder_sigkill``: recorder_node is SIGKILLed mid-episode. Survived: the episode is
  readable after ``equidiff bags repair`` and franka_node did not notice.
* ``gripper_stuck``: franky-sim's hand is jammed (the fingers stay and the gripper command
  never finishes) while a new width is sent and the arm moves 3 cm. Survived: the fingers did
  not move (the fault took), the arm reached its target (< 5 mm) and its state kept coming (no
  gap longer than half the 6 s jam: a control loop waiting on the gripper would stall until the
  jam clears; a loaded machine starves it for over a second at times), and after the jam clears
  a new width is reached.
* between faults the arm goes back home through franka_node's ``/franka/home`` (refused, and
  the campaign's next fault then fails, if a stop still awaited acknowledgement).
* ``franka_node_killed``: SIGKILL while the arm runs a chunk; the sender keeps publishing
  chunks that start where the arm is. franka_node is started again (same ``run_dir``): it
  must find the unclean exit, not move and hold; chunks are refused until /franka/acknowledge,
  after which the arm follows them again. Survived: all of that.

Across the campaign: ``max_excursion_mm`` (largest distance of the measured TCP outside the
safety box), ``auto_resumes`` (times the arm moved or a chunk was accepted while franka_node
awaited an acknowledgement: must be 0) and ``episodes_lost`` (recorded episodes that cannot be
read, after repair: must be 0). Baseline in the same run: the arm's drift while holding still
before any fault (``baseline_hold_drift_mm``), against which ``--still-mm`` is set.

Prints one JSON line. ``--keep DIR`` keeps the logs and episodes: written beside DIR and renamed to it
when the campaign ends (failed faults included; a crash leaves nothing); an existing DIR holding
anything is refused (exit 2) before anything starts, unless ``--force``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from equidiff_core.benches.fault_campaign import FAULTS, run_bench
from equidiff_core.runtime.jobs import progress_lines
from equidiff_ros.benches.safety_probe import SafetyProbe
from equidiff_ros.commands import add_force_argument


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.epilog = __doc__.split("\n", 1)[1]
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument(
        "--faults", default=",".join(FAULTS), help=f"comma-separated subset of {', '.join(FAULTS)} (default: all)"
    )
    parser.add_argument(
        "--still-mm", type=float, default=3.0, help="the arm 'held still' when it moved less than this (default 3 mm)"
    )
    parser.add_argument(
        "--control-config",
        type=Path,
        default=None,
        help="franka_node's control.yaml for this run (default: config/control.yaml)",
    )
    parser.add_argument(
        "--box-margin-mm",
        type=float,
        default=None,
        help="franka_node's safety.box_margin_m for this run, in mm (default: control.yaml's); "
        "0 measures the raw overshoot past the box",
    )
    parser.add_argument(
        "--policy",
        choices=["shipped", "standin"],
        default="shipped",
        help="policy_node's checkpoint for the policy faults (default: the shipped one if present)",
    )
    parser.add_argument("--domain-id", type=int, default=None, help="ROS_DOMAIN_ID (default: a random private one)")
    parser.add_argument(
        "--keep", type=Path, default=None, help="keep logs and episodes in this new folder (default: a temp dir)"
    )
    add_force_argument(parser)


def run(args: argparse.Namespace) -> int:
    with progress_lines("stderr"):  # stdout holds the JSON line
        result = run_bench(
            args.faults,
            SafetyProbe(),
            still_mm=args.still_mm,
            box_margin_mm=args.box_margin_mm,
            policy=args.policy,
            control_config=args.control_config,
            domain_id=args.domain_id,
            keep=args.keep,
            force=args.force,
        )
    print(json.dumps(result))
    return 0
