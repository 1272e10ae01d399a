"""Camera calibration's two commands, lab or twin: ``equidiff calibrate cameras`` (extrinsics from a ChArUco
board the arm carries, written to a new lab file) and ``equidiff calibrate check`` (each camera's alignment
against the other clouds and the fingertips). Their help texts say what each does; the calibration itself is
``equidiff_core.calibration``, its twin side ``equidiff_core.twin.calibration``. A job of both (the lab and the
twin), so it sits above them, as ``training_job`` does.
"""

from __future__ import annotations

import json
import sys
from contextlib import nullcontext

import numpy as np

from equidiff_core.calibration.board import BoardSpec, CalibrationError, write_printable
from equidiff_core.calibration.capture import FrankyArm, RealSenseColour, capture_samples
from equidiff_core.calibration.check import check_alignment, log_check
from equidiff_core.calibration.labfile import write_calibrated_lab
from equidiff_core.calibration.limits import MotionLimits
from equidiff_core.calibration.operator import capture_operator
from equidiff_core.calibration.plan import PlanConfig, plan_poses
from equidiff_core.calibration.solve import calibrate
from equidiff_core.cameras import make_camera
from equidiff_core.cameras.base import CameraError
from equidiff_core.cameras.twin import TwinCamera
from equidiff_core.config import ConfigError, default_config_dir, load_lab_config
from equidiff_core.output_files import refuse_existing, staged_output
from equidiff_core.robots.base import RobotError
from equidiff_core.robots.franky import FrankyRobot
from equidiff_core.robots.franky.hand import finger_width
from equidiff_core.twin.calibration import DirectSimArm, FrankyTwinArm, calibrate_twin, nominal_mount
from equidiff_core.twin.config import load_twin_config
from equidiff_core.viz.logger import open_recording


def board_spec(args) -> BoardSpec:
    """The board the command's --squares, --square-mm, --marker-mm and --dictionary describe."""
    return BoardSpec(args.squares[0], args.squares[1], args.square_mm / 1000, args.marker_mm / 1000, args.dictionary)


def _log(message: str) -> None:
    """Progress and errors go to stderr: stdout holds the one JSON line."""
    print(message, file=sys.stderr, flush=True)


def run_camera_calibration(args) -> int:
    """``equidiff calibrate cameras`` for its parsed arguments: the board, the lab or the twin; the exit status."""
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
    return PlanConfig(poses=args.poses, max_tilt_deg=args.max_tilt, max_yaw_deg=args.max_yaw, seed=args.seed)


def _run_twin(args, spec, lab, lab_path) -> int:
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
        _write_lab(lab_path, result, args)
        report["output"] = str(args.output)
    print(json.dumps(report))
    return 0


def _write_lab(lab_path, result, args) -> None:
    """lab.yaml with the solved extrinsics, to ``args.output`` (``--force`` to overwrite)."""
    T = {n: c.T_base_cam for n, c in result.cameras.items()}
    write_calibrated_lab(lab_path, T, args.output, force=args.force, notes=_notes(result))


def _notes(result) -> list[str]:
    return [
        f"{name}: reprojection RMS {c.rms_px:.3f} px ({c.rms_mm:.3f} mm at the board), "
        f"{c.detections} poses, {c.corners} corners"
        for name, c in result.cameras.items()
    ]


def _run_lab(args, spec, lab, lab_path) -> int:
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
    _write_lab(lab_path, result, args)
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


def _twin_capture(args, lab):
    """(clouds with colours, measured TCP, gripper width) from the twin's cameras at their true poses."""
    truth = load_lab_config(args.truth or default_config_dir() / "lab.yaml")
    cfg = load_twin_config(args.twin_config)
    T = np.eye(4)
    T[:3, :3] = np.diag([1.0, -1.0, -1.0])
    T[:3, 3] = args.tcp
    if args.direct:
        arm = DirectSimArm(cfg, gripper_width=args.width)
        measured, qpos = arm.move_to(T)
    else:
        arm = FrankyTwinArm(cfg, MotionLimits.load(truth, args.control_config))
        measured, qpos = arm.move_to(T)
    try:
        width = finger_width(arm.model, qpos)
    finally:
        arm.close()
    clouds = {}
    for cam in truth.cameras:
        if cam.name not in {c.name for c in lab.cameras}:
            continue
        with TwinCamera(cam, state_source=lambda t: (qpos, 0.0, 0), paced=False, twin_config=cfg) as c:
            frame = c.read()
        clouds[cam.name] = (frame.points, frame.colors)
    return clouds, measured, width


def _lab_capture(lab):
    robot = FrankyRobot(lab.robot.ip, gripper=True)  # read only: nothing moves
    robot.connect()
    try:
        state = robot.read_state()
        tcp, width = state.ee_pose, state.gripper_width
    finally:
        robot.disconnect()
    clouds = {}
    for cam in lab.cameras:
        with make_camera("realsense", cam) as c:
            frame = c.read(timeout_s=5.0)
        clouds[cam.name] = (frame.points, frame.colors)
    return clouds, tcp, width


def run_calibration_check(args) -> int:
    """``equidiff calibrate check`` for its parsed arguments: one JSON line; 3 when a camera is beyond tolerance."""
    rrd = None if args.spawn else args.rrd
    if rrd is not None:  # refused before anything moves or captures
        refuse_existing(rrd, args.force)
    try:
        lab_path = args.lab or default_config_dir() / "lab.yaml"
        lab = load_lab_config(lab_path)
        clouds, tcp, width = _twin_capture(args, lab) if args.twin else _lab_capture(lab)
    except (CalibrationError, ConfigError, CameraError, RobotError) as err:
        _log(f"equidiff calibrate check: {err}")
        return 1
    results = check_alignment(lab, {n: p for n, (p, _) in clouds.items()}, tcp, width)
    if rrd is not None or args.spawn:
        with staged_output(rrd, force=args.force) if rrd is not None else nullcontext() as staged:
            rec = open_recording("calibration_check", spawn=args.spawn, save=staged.path if staged else None)
            log_check(rec, lab, clouds, results, tcp, width)
            rec.flush()
            rec.disconnect()
    worst = {
        key: max((getattr(r, key) for r in results.values() if getattr(r, key) is not None), default=None)
        for key in ("cloud_to_cloud_mm", "fingertips_mm")
    }
    print(
        json.dumps(
            {
                "lab": str(lab_path),
                "max_cloud_to_cloud_mm": worst["cloud_to_cloud_mm"],
                "max_fingertips_mm": worst["fingertips_mm"],
                "cameras": {n: r.summary() for n, r in results.items()},
                "tcp_xyz": [round(float(v), 4) for v in tcp[:3, 3]],
                "gripper_width": None if width is None or not np.isfinite(width) else round(float(width), 4),
                "tolerance_mm": args.tolerance_mm,
                **({"rrd": str(args.rrd)} if args.rrd else {}),
            }
        )
    )
    beyond = [v for v in worst.values() if v is not None and v > args.tolerance_mm]
    return 3 if beyond else 0
