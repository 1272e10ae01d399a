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
import json
import sys
from pathlib import Path


def add_board_arguments(parser: argparse.ArgumentParser) -> None:
    from equidiff_core.calibration.board import BoardSpec

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


def board_spec(args: argparse.Namespace):
    from equidiff_core.calibration.board import BoardSpec

    return BoardSpec(args.squares[0], args.squares[1], args.square_mm / 1000, args.marker_mm / 1000, args.dictionary)


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
    parser.add_argument("--force", action="store_true", help="replace --output if it exists (the old one is backed up)")
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


def _log(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def run(args: argparse.Namespace) -> int:
    from equidiff_core.calibration.board import CalibrationError, write_printable
    from equidiff_core.config import ConfigError, default_config_dir, load_lab_config
    from equidiff_core.robots.base import RobotError

    try:
        spec = board_spec(args)
        if args.write_board is not None:
            printed = write_printable(spec, args.write_board, dpi=args.dpi)
            _log(printed.instructions())
            print(
                json.dumps(
                    {
                        "board": str(printed.path),
                        "page_mm": [round(v, 2) for v in printed.page_mm],
                        "board_mm": [round(v, 2) for v in printed.board_mm],
                        "square_mm": printed.square_mm,
                        "marker_mm": printed.marker_mm,
                        "squares": [spec.squares_x, spec.squares_y],
                        "dictionary": spec.dictionary,
                    }
                )
            )
            return 0
        lab_path = args.lab or default_config_dir() / "lab.yaml"
        lab = load_lab_config(lab_path)
        if args.twin:
            return _run_twin(args, spec, lab, lab_path)
        if args.output is None:
            _log("equidiff calibrate cameras: --output is required (the calibrated lab file to write)")
            return 2
        if args.output.exists() and not args.force:  # fail before the arm moves, not after
            raise CalibrationError(
                f"{args.output} exists and is left as it is: choose a new --output, "
                "or pass --force to replace it (the old file is then kept as a .bak copy)"
            )
        return _run_lab(args, spec, lab, lab_path)
    except (CalibrationError, ConfigError, RobotError, ValueError) as err:
        _log(f"equidiff calibrate cameras: {err}")
        return 1


def _plan_config(args):
    from equidiff_core.calibration.plan import PlanConfig

    return PlanConfig(poses=args.poses, max_tilt_deg=args.max_tilt, max_yaw_deg=args.max_yaw, seed=args.seed)


def _run_twin(args, spec, lab, lab_path) -> int:
    from equidiff_core.calibration.labfile import write_calibrated_lab
    from equidiff_core.calibration.limits import MotionLimits
    from equidiff_core.twin.calibration import calibrate_twin
    from equidiff_core.twin.config import load_twin_config

    report, result, _ = calibrate_twin(
        lab,
        load_twin_config(args.twin_config),
        spec,
        _plan_config(args),
        arm="direct" if args.direct else "franky",
        perturb_m=args.perturb_mm / 1000,
        perturb_deg=args.perturb_deg,
        log=_log,
        limits=MotionLimits.load(lab, args.control_config),
    )
    if args.output is not None:
        write_calibrated_lab(
            lab_path,
            {n: c.T_base_cam for n, c in result.cameras.items()},
            args.output,
            force=args.force,
            notes=_notes(result),
        )
        report["output"] = str(args.output)
    print(json.dumps(report))
    return 0


def _notes(result) -> list[str]:
    return [
        f"{name}: reprojection RMS {c.rms_px:.3f} px ({c.rms_mm:.3f} mm at the board), "
        f"{c.detections} poses, {c.corners} corners"
        for name, c in result.cameras.items()
    ]


def _run_lab(args, spec, lab, lab_path) -> int:
    from equidiff_core.calibration.capture import (
        FrankyArm,
        RealSenseColour,
        capture_samples,
    )
    from equidiff_core.calibration.labfile import write_calibrated_lab
    from equidiff_core.calibration.limits import MotionLimits
    from equidiff_core.calibration.plan import plan_poses
    from equidiff_core.calibration.solve import calibrate
    from equidiff_core.twin.calibration import nominal_mount

    limits = MotionLimits.load(lab, args.control_config)
    cams = []
    arm = None
    try:
        for cam in lab.cameras:
            cams.append(RealSenseColour(cam))
        models = [c.model for c in cams]

        def grab(_state):
            return {c.name: c.grab() for c in cams}

        arm = FrankyArm(lab.robot.ip, limits)
        if args.operator:
            from equidiff_core.calibration.operator import capture_operator

            samples = capture_operator(arm, grab, spec, lab.workspace, log=_log)
        else:
            poses = plan_poses(
                lab, models, spec, nominal_mount(spec), _plan_config(args), start=arm.tcp_pose(), limits=limits
            )
            if not args.yes:
                home = " first to control.yaml's home pose, then" if limits.control.home_on_start else ""
                _log(
                    f"The arm will move{home} to {len(poses)} poses around the workspace at up to "
                    f"{arm.speed_m_s * 100:.0f} cm/s with the board on its hand. Keep the area clear; press "
                    "Enter to start, Ctrl-C to abort."
                )
                input()
            samples = capture_samples(arm, poses, grab, spec, limits, log=_log)
    finally:
        if arm is not None:
            arm.close()
        for c in cams:
            c.close()
    result = calibrate(spec, models, samples)
    write_calibrated_lab(
        lab_path,
        {n: c.T_base_cam for n, c in result.cameras.items()},
        args.output,
        force=args.force,
        notes=_notes(result),
    )
    _log(f"wrote {args.output}")
    print(
        json.dumps(
            {
                "output": str(args.output),
                "poses": len(samples),
                "cameras": {n: c.summary() for n, c in result.cameras.items()},
            }
        )
    )
    return 0
