"""`equidiff calibrate check`: how far each camera's cloud is from known geometry, in mm.

    equidiff calibrate check --lab config/lab_calibrated.yaml --rrd check.rrd   # the lab, arm held still
    equidiff calibrate check --twin --lab config/lab_calibrated.yaml            # the twin's cameras

Each camera's cloud is moved into the base frame with the extrinsics in ``--lab`` and compared
with (1) the other cameras' clouds (median point-to-plane distance where the views overlap)
and (2) the FR3's fingertips placed at the TCP pose the robot reports (median distance of the
camera's points on the fingers to the fingers' surface). One JSON line; ``--rrd`` / ``--spawn``
show the clouds, camera frames and the finger model in rerun (``--rrd FILE`` is written beside
itself and renamed into place; an existing FILE is refused, exit 2, before anything is captured,
unless ``--force``). Exit status 3 when a camera is beyond ``--tolerance-mm``.

On the robot: nothing moves. Put the open gripper where every camera sees it, stop the
camera and franka nodes (this command opens the devices itself) and run it.
``--twin``: the twin's cameras stand at the poses of ``--truth`` (default config/lab.yaml); the
arm is taken to ``--tcp`` by franka_node's control loop with franky against franky-sim
(``--direct``: in-process sim).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from equidiff_core.calibration.job import CalibrationCheckSettings, beyond_tolerance, run_calibration_check
from equidiff_core.runtime.jobs import progress_lines
from equidiff_ros.commands import add_force_argument, print_result


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.epilog = __doc__.split("\n", 1)[1]
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("--lab", type=Path, default=None, help="lab file whose extrinsics are checked")
    parser.add_argument("--tolerance-mm", type=float, default=2.0, help="exit 3 if a camera's median is above this")
    parser.add_argument(
        "--rrd", type=Path, default=None, help="save the rerun view to this .rrd (refused if it exists)"
    )
    add_force_argument(parser)
    parser.add_argument("--spawn", action="store_true", help="open a rerun viewer")
    parser.add_argument("--twin", action="store_true", help="check against the digital twin's cameras")
    parser.add_argument("--truth", type=Path, default=None, help="twin: where its cameras really are")
    parser.add_argument("--twin-config", type=Path, default=None)
    parser.add_argument("--direct", action="store_true", help="twin: in-process sim instead of franky + franky-sim")
    parser.add_argument(
        "--control-config",
        type=Path,
        default=None,
        help="twin: franka_node's control.yaml for the move to --tcp (default: the project's)",
    )
    parser.add_argument(
        "--tcp",
        type=float,
        nargs=3,
        default=(0.45, 0.0, 0.25),
        metavar=("X", "Y", "Z"),
        help="twin: TCP position for the check (gripper pointing down)",
    )
    parser.add_argument("--width", type=float, default=0.04, help="twin: gripper opening, m")


def run(args: argparse.Namespace) -> int:
    settings = CalibrationCheckSettings(
        lab=args.lab,
        tolerance_mm=args.tolerance_mm,
        rrd=args.rrd,
        spawn=args.spawn,
        twin=args.twin,
        truth=args.truth,
        twin_config=args.twin_config,
        direct=args.direct,
        control_config=args.control_config,
        tcp=tuple(args.tcp),
        width=args.width,
        force=args.force,
    )
    with progress_lines("stderr"):  # stdout holds the JSON line
        report = run_calibration_check(settings)
    print_result(report)
    return 3 if beyond_tolerance(report) else 0
