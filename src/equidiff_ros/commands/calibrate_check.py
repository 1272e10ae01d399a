"""`equidiff calibrate check`: how far each camera's cloud is from known geometry, in mm.

    equidiff calibrate check --lab config/lab_calibrated.yaml --rrd check.rrd   # the lab, arm held still
    equidiff calibrate check --twin --lab config/lab_calibrated.yaml            # the twin's cameras

Each camera's cloud is moved into the base frame with the extrinsics in ``--lab`` and compared
with (1) the other cameras' clouds (median point-to-plane distance where the views overlap)
and (2) the FR3's fingertips placed at the TCP pose the robot reports (median distance of the
camera's points on the fingers to the fingers' surface). One JSON line; ``--rrd`` / ``--spawn``
show the clouds, camera frames and the finger model in rerun. Exit status 3 when a camera is
beyond ``--tolerance-mm``.

On the robot: nothing moves. Put the open gripper where every camera sees it, stop the
camera and franka nodes (this command opens the devices itself) and run it.
``--twin``: the twin's cameras stand at the poses of ``--truth`` (default config/lab.yaml); the
arm is taken to ``--tcp`` by franka_node's control loop with franky against franky-sim
(``--direct``: in-process sim).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.epilog = __doc__.split("\n", 1)[1]
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("--lab", type=Path, default=None, help="lab file whose extrinsics are checked")
    parser.add_argument("--tolerance-mm", type=float, default=2.0, help="exit 3 if a camera's median is above this")
    parser.add_argument("--rrd", type=Path, default=None, help="save the rerun view to this .rrd")
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


def _log(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def _twin_capture(args, lab):
    """(clouds with colours, measured TCP, gripper width) from the twin's cameras at their true poses."""
    import mujoco

    from equidiff_core.calibration.limits import MotionLimits
    from equidiff_core.cameras.twin import TwinCamera
    from equidiff_core.config import default_config_dir, load_lab_config
    from equidiff_core.twin.calibration import DirectSimArm, FrankyTwinArm
    from equidiff_core.twin.config import load_twin_config

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
        model = arm.model
        width = float(
            sum(
                qpos[model.jnt_qposadr[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, j)]]
                for j in ("robot0_finger_joint1", "robot0_finger_joint2")
            )
        )
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
    from equidiff_core.cameras import make_camera
    from equidiff_core.robots.franky import FrankyRobot

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


def run(args: argparse.Namespace) -> int:
    from equidiff_core.calibration.board import CalibrationError
    from equidiff_core.calibration.check import check_alignment, log_check
    from equidiff_core.cameras.base import CameraError
    from equidiff_core.config import ConfigError, default_config_dir, load_lab_config
    from equidiff_core.robots.base import RobotError

    try:
        lab_path = args.lab or default_config_dir() / "lab.yaml"
        lab = load_lab_config(lab_path)
        clouds, tcp, width = _twin_capture(args, lab) if args.twin else _lab_capture(lab)
    except (CalibrationError, ConfigError, CameraError, RobotError) as err:
        _log(f"equidiff calibrate check: {err}")
        return 1
    results = check_alignment(lab, {n: p for n, (p, _) in clouds.items()}, tcp, width)
    if args.rrd is not None or args.spawn:
        from equidiff_core.viz.logger import open_recording

        rec = open_recording("calibration_check", spawn=args.spawn, save=None if args.spawn else args.rrd)
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
