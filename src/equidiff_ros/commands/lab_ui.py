"""`equidiff lab`: the operator loop in the terminal, beside `ros2 launch` (or the twin).

One screen shows the robot's state and last fault, the recorder and the episode count, the
policy and the SpaceMouse; single keys start, keep (success or failure) and discard episodes,
home the arm, switch the policy, hand the arm to the SpaceMouse and acknowledge a stop. After
each episode the arm goes home and a reset countdown runs (--reset-s; --auto-start starts the
next episode when it ends). The keys and the rules are in equidiff_core.lab.operator_loop and
docs/lab.md, "The operator loop".

A client of the running nodes, through their services and latched topics (the same as
`equidiff lab record|policy|home|ack|status`, which stay for scripts): quitting it stops nothing.
"""

from __future__ import annotations

from pathlib import Path

from equidiff_ros.lab_screen import run_lab_screen


def add_arguments(parser) -> None:
    parser.epilog = __doc__.split("\n", 1)[1]
    parser.add_argument(
        "--reset-s", type=float, default=10.0, help="the reset countdown after each episode, seconds (10)"
    )
    parser.add_argument(
        "--auto-start",
        action="store_true",
        help="start the next episode when the countdown ends and the arm holds (never enables the policy)",
    )
    parser.add_argument("--no-home", action="store_true", help="do not home the arm when an episode ends")
    parser.add_argument(
        "--output-dir",
        type=Path,
        help="the recorder's output folder, to count its episodes (default: learned from the recorder's paths)",
    )


def run(args) -> int:
    return run_lab_screen(args)
