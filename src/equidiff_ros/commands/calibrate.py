"""`equidiff calibrate cameras`: every camera's T_base_optical from a ChArUco board the arm carries.

    equidiff calibrate cameras --write-board board.pdf        # print it at 100 %, measure a square
    equidiff calibrate cameras --output config/lab_calibrated.yaml          # the lab: planned poses
    equidiff calibrate cameras --output config/lab_calibrated.yaml --operator   # SpaceMouse-driven poses
    equidiff calibrate cameras --twin                         # verify in the digital twin (one JSON line)

The board is fixed to the hand, printed side facing back up the fingers, beside the hand
(see docs/perception.md). Planned poses stay in the workspace box where it overlaps lab.yaml's
``safety_box``, within control.yaml's orientation cone, and are chosen so that every camera
should see the whole board, judged with the extrinsics in ``--lab`` (rough hand-typed numbers
suffice). A pose outside those limits is an error before anything moves. The arm is moved by
franka_node's own control loop (stop franka_node first): it homes as franka_node does, then
glides between poses with the safety box, cone and speed limits of ``--control-config``; a
robot error or a divergence stop aborts the calibration.
Each camera is solved by closed-form eye-to-hand calibration, then all cameras and the
board's place on the hand are refined together by minimising the corners' reprojection
error. The result goes to a new lab file (an existing one is kept unless ``--force``; it is
then backed up) and one JSON line reports each camera's reprojection error in px and mm.

``--twin``: the twin's cameras stand where ``--lab`` says (the ground truth); the calibration
starts from guesses perturbed by ``--perturb-mm`` / ``--perturb-deg``, drives franky against
franky-sim (``--direct``: an in-process sim, faster) and prints the errors against the truth
as ``max_translation_error_mm`` / ``max_rotation_error_deg``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from equidiff_core.calibration.board import BoardSpec
from equidiff_core.calibration.job import CameraCalibrationSettings, run_camera_calibration
from equidiff_core.runtime.jobs import progress_lines
from equidiff_ros.commands import add_force_argument, print_result


def add_board_arguments(parser: argparse.ArgumentParser) -> None:
    d = BoardSpec()
    parser.add_argument(
        "--squares",
        type=int,
        nargs=2,
        default=(d.squares_x, d.squares_y),
        metavar=("X", "Y"),
        help="board squares across and down",
    )
    parser.add_argument(
        "--square-mm", type=float, default=d.square_length * 1000, help="square side as printed (measure it)"
    )
    parser.add_argument("--marker-mm", type=float, default=d.marker_length * 1000)
    parser.add_argument("--dictionary", default=d.dictionary)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.epilog = __doc__.split("\n", 1)[1]
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument(
        "--lab",
        type=Path,
        default=None,
        help="current lab file: the cameras' rough extrinsics (twin: the ground truth)",
    )
    parser.add_argument("--output", type=Path, default=None, help="new lab file with the calibrated extrinsics")
    parser.add_argument(
        "--control-config",
        type=Path,
        default=None,
        help="franka_node's control.yaml: limits, home pose and franky settings for the moves (default: the project's)",
    )
    add_force_argument(
        parser, "replace --output if it exists, once the new file is complete (the old one is backed up)"
    )
    parser.add_argument(
        "--write-board",
        type=Path,
        default=None,
        metavar="FILE",
        help="write the printable board (.pdf or .png) and exit",
    )
    parser.add_argument(
        "--dpi",
        type=int,
        default=508,
        help="print resolution; 508 dpi = 20 px/mm, so whole-mm squares are whole pixels",
    )
    add_board_arguments(parser)
    parser.add_argument("--poses", type=int, default=20, help="planned poses")
    parser.add_argument("--max-tilt", type=float, default=20.0, help="deg, board tilt from horizontal")
    parser.add_argument("--max-yaw", type=float, default=45.0, help="deg, turn about the vertical")
    parser.add_argument("--seed", type=int, default=0, help="pose plan (and twin perturbation) seed")
    parser.add_argument(
        "--operator",
        action="store_true",
        help="drive the arm with the SpaceMouse; left button captures, right button finishes",
    )
    parser.add_argument("--yes", action="store_true", help="do not ask before moving the arm")
    parser.add_argument("--twin", action="store_true", help="calibrate the digital twin's cameras and report errors")
    parser.add_argument("--twin-config", type=Path, default=None)
    parser.add_argument("--direct", action="store_true", help="twin: in-process sim instead of franky + franky-sim")
    parser.add_argument("--perturb-mm", type=float, default=30.0, help="twin: initial guess offset")
    parser.add_argument("--perturb-deg", type=float, default=3.0, help="twin: initial guess rotation")


def _wait_for_enter(message: str) -> None:
    """What the arm is about to do, on stderr (stdout holds the JSON line); returns on Enter."""
    print(message, file=sys.stderr, flush=True)
    input()


def run(args: argparse.Namespace) -> int:
    settings = CameraCalibrationSettings(
        squares=tuple(args.squares),
        square_mm=args.square_mm,
        marker_mm=args.marker_mm,
        dictionary=args.dictionary,
        write_board=args.write_board,
        dpi=args.dpi,
        lab=args.lab,
        output=args.output,
        force=args.force,
        control_config=args.control_config,
        poses=args.poses,
        max_tilt=args.max_tilt,
        max_yaw=args.max_yaw,
        seed=args.seed,
        operator=args.operator,
        yes=args.yes,
        twin=args.twin,
        twin_config=args.twin_config,
        direct=args.direct,
        perturb_mm=args.perturb_mm,
        perturb_deg=args.perturb_deg,
    )
    with progress_lines("stderr"):  # stdout holds the JSON line
        result = run_camera_calibration(settings, confirm=_wait_for_enter)
    return print_result(result, "calibrate cameras")
