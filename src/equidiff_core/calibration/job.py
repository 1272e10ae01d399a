"""Camera calibration's two commands, lab or twin: ``equidiff calibrate cameras`` (extrinsics from a ChArUco
board the arm carries, written to a new lab file) and ``equidiff calibrate check`` (each camera's alignment
against the other clouds and the fingertips). Their help texts say what each does; the calibration itself is
``equidiff_core.calibration``, its twin side ``equidiff_core.twin.calibration``. A job of both (the lab and the
twin), as ``training.job`` is ``equidiff train``'s. Each takes its settings and returns its JSON line as a
dict, or raises ``CalibrationJobError``; progress goes to this module's logger.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from contextlib import nullcontext
from dataclasses import dataclass
from pathlib import Path

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
from equidiff_core.robots.base import RobotError
from equidiff_core.robots.franky import FrankyRobot
from equidiff_core.robots.franky.hand import finger_width
from equidiff_core.runtime.jobs import JobError
from equidiff_core.runtime.output_files import refuse_existing, staged_output
from equidiff_core.twin.calibration import DirectSimArm, FrankyTwinArm, calibrate_twin, nominal_mount
from equidiff_core.twin.config import load_twin_config
from equidiff_core.viz.recording_setup import open_recording

logger = logging.getLogger(__name__)


class CalibrationJobError(JobError):
    """A calibration command could not run: exit status 2 when ``equidiff calibrate cameras`` has no output
    file to write, 1 for anything else (the board, the config, the robot, the cameras, an existing output)."""


@dataclass(frozen=True)
class CameraCalibrationSettings:
    """``equidiff calibrate cameras``' settings: its flags, same names (the command's help says more)."""

    squares: tuple[int, int]  # the board's squares, X and Y
    square_mm: float  # square side as printed
    marker_mm: float  # marker side as printed
    dictionary: str  # the ArUco dictionary
    write_board: Path | None  # write the printable board here and stop
    dpi: int  # the printable board's resolution
    lab: Path | None  # the lab file whose cameras are calibrated (None: the installed one)
    output: Path | None  # the new lab file with the calibrated extrinsics
    force: bool  # replace ``output`` if it exists
    control_config: Path | None  # control.yaml: the arm's limits (None: the installed one)
    poses: int  # planned poses
    max_tilt: float  # deg, board tilt from horizontal
    max_yaw: float  # deg, turn about the vertical
    seed: int  # the pose plan's (and the twin perturbation's) seed
    operator: bool  # the operator moves the arm by hand instead of the plan
    yes: bool  # do not ask before moving the arm
    twin: bool  # calibrate the digital twin's cameras and report the errors
    twin_config: Path | None  # twin.yaml (None: the installed one)
    direct: bool  # twin: the in-process sim instead of franky + franky-sim
    perturb_mm: float  # twin: the initial guess's offset
    perturb_deg: float  # twin: the initial guess's rotation


@dataclass(frozen=True)
class CalibrationCheckSettings:
    """``equidiff calibrate check``'s settings: its flags, same names (the command's help says more)."""

    lab: Path | None  # the lab file whose extrinsics are checked (None: the installed one)
    tolerance_mm: float  # a camera's median above this is beyond tolerance
    rrd: Path | None  # save the rerun view here
    spawn: bool  # open a rerun viewer
    twin: bool  # check against the digital twin's cameras
    truth: Path | None  # twin: the lab file where its cameras really are (None: the installed one)
    twin_config: Path | None  # twin.yaml (None: the installed one)
    direct: bool  # twin: the in-process sim instead of franky + franky-sim
    control_config: Path | None  # control.yaml: the arm's limits (None: the installed one)
    tcp: tuple[float, float, float]  # twin: where the arm is taken, base frame, m
    width: float  # twin: gripper opening, m
    force: bool = False  # replace an existing ``rrd``


def board_spec(settings: CameraCalibrationSettings) -> BoardSpec:
    """The board the settings' squares, square and marker sides and dictionary describe."""
    return BoardSpec(
        settings.squares[0],
        settings.squares[1],
        settings.square_mm / 1000,
        settings.marker_mm / 1000,
        settings.dictionary,
    )


def run_camera_calibration(settings: CameraCalibrationSettings, confirm: Callable[[str], None] | None = None) -> dict:
    """The printable board, the lab's or the twin's calibration: the command's JSON line. Before the arm moves
    on a plan (the lab, without ``yes``) ``confirm`` is called with what will happen and returns once the
    operator agreed (it raises to abort)."""
    try:
        spec = board_spec(settings)
        if settings.write_board is not None:
            printed = write_printable(spec, settings.write_board, dpi=settings.dpi)
            logger.info(printed.instructions())
            return {
                "board": str(printed.path),
                "page_mm": [round(v, 2) for v in printed.page_mm],
                "board_mm": [round(v, 2) for v in printed.board_mm],
                "square_mm": printed.square_mm,
                "marker_mm": printed.marker_mm,
                "squares": [spec.squares_x, spec.squares_y],
                "dictionary": spec.dictionary,
            }
        lab_path = settings.lab or default_config_dir() / "lab.yaml"
        lab = load_lab_config(lab_path)
        if settings.twin:
            return _run_twin(settings, spec, lab, lab_path)
        if settings.output is None:
            raise CalibrationJobError("--output is required (the calibrated lab file to write)", 2)
        if settings.output.exists() and not settings.force:  # fail before the arm moves, not after
            raise CalibrationError(
                f"{settings.output} exists and is left as it is: choose a new --output, "
                "or pass --force to replace it (the old file is then kept as a .bak copy)"
            )
        if not (settings.yes or settings.operator) and confirm is None:
            raise CalibrationError("the arm would move without asking: pass --yes, or a confirm callback")
        return _run_lab(settings, spec, lab, lab_path, confirm)
    except (CalibrationError, ConfigError, RobotError, ValueError) as err:
        raise CalibrationJobError(str(err)) from err


def _plan_config(settings):
    return PlanConfig(
        poses=settings.poses, max_tilt_deg=settings.max_tilt, max_yaw_deg=settings.max_yaw, seed=settings.seed
    )


def _run_twin(settings, spec, lab, lab_path) -> dict:
    report, result, _ = calibrate_twin(
        lab,
        load_twin_config(settings.twin_config),
        spec,
        _plan_config(settings),
        arm="direct" if settings.direct else "franky",
        perturb_m=settings.perturb_mm / 1000,
        perturb_deg=settings.perturb_deg,
        log=logger.info,
        limits=MotionLimits.load(lab, settings.control_config),
    )
    if settings.output is not None:
        _write_lab(lab_path, result, settings)
        report["output"] = str(settings.output)
    return report


def _write_lab(lab_path, result, settings) -> None:
    """lab.yaml with the solved extrinsics, to ``settings.output`` (``--force`` to overwrite)."""
    T = {n: c.T_base_cam for n, c in result.cameras.items()}
    write_calibrated_lab(lab_path, T, settings.output, force=settings.force, notes=_notes(result))


def _notes(result) -> list[str]:
    return [
        f"{name}: reprojection RMS {c.rms_px:.3f} px ({c.rms_mm:.3f} mm at the board), "
        f"{c.detections} poses, {c.corners} corners"
        for name, c in result.cameras.items()
    ]


def _run_lab(settings, spec, lab, lab_path, confirm: Callable[[str], None] | None) -> dict:
    limits = MotionLimits.load(lab, settings.control_config)
    cams = []
    arm = None
    try:
        for cam in lab.cameras:
            cams.append(RealSenseColour(cam))
        models = [c.model for c in cams]

        def grab(_state):
            return {c.name: c.grab() for c in cams}

        arm = FrankyArm(lab.robot.ip, limits)
        if settings.operator:
            samples = capture_operator(arm, grab, spec, lab.workspace, log=logger.info)
        else:
            poses = plan_poses(
                lab, models, spec, nominal_mount(spec), _plan_config(settings), start=arm.tcp_pose(), limits=limits
            )
            if not settings.yes:
                home = " first to control.yaml's home pose, then" if limits.control.home_on_start else ""
                confirm(
                    f"The arm will move{home} to {len(poses)} poses around the workspace at up to "
                    f"{arm.speed_m_s * 100:.0f} cm/s with the board on its hand. Keep the area clear; press "
                    "Enter to start, Ctrl-C to abort."
                )
            samples = capture_samples(arm, poses, grab, spec, limits, log=logger.info)
    finally:
        if arm is not None:
            arm.close()
        for c in cams:
            c.close()
    result = calibrate(spec, models, samples)
    _write_lab(lab_path, result, settings)
    logger.info(f"wrote {settings.output}")
    return {
        "output": str(settings.output),
        "poses": len(samples),
        "cameras": {n: c.summary() for n, c in result.cameras.items()},
    }


def _twin_capture(settings, lab):
    """(clouds with colours, measured TCP, gripper width) from the twin's cameras at their true poses."""
    truth = load_lab_config(settings.truth or default_config_dir() / "lab.yaml")
    cfg = load_twin_config(settings.twin_config)
    T = np.eye(4)
    T[:3, :3] = np.diag([1.0, -1.0, -1.0])
    T[:3, 3] = settings.tcp
    if settings.direct:
        arm = DirectSimArm(cfg, gripper_width=settings.width)
        measured, qpos = arm.move_to(T)
    else:
        arm = FrankyTwinArm(cfg, MotionLimits.load(truth, settings.control_config))
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


def run_calibration_check(settings: CalibrationCheckSettings) -> dict:
    """Each camera's alignment: the command's JSON line (``beyond_tolerance`` says whether a camera is beyond
    ``tolerance_mm``: the command exits 3)."""
    rrd = None if settings.spawn else settings.rrd
    if rrd is not None:  # refused before anything moves or captures
        refuse_existing(rrd, settings.force)
    try:
        lab_path = settings.lab or default_config_dir() / "lab.yaml"
        lab = load_lab_config(lab_path)
        clouds, tcp, width = _twin_capture(settings, lab) if settings.twin else _lab_capture(lab)
    except (CalibrationError, ConfigError, CameraError, RobotError) as err:
        raise CalibrationJobError(str(err)) from err
    results = check_alignment(lab, {n: p for n, (p, _) in clouds.items()}, tcp, width)
    if rrd is not None or settings.spawn:
        with staged_output(rrd, force=settings.force) if rrd is not None else nullcontext() as staged:
            rec = open_recording("calibration_check", spawn=settings.spawn, save=staged.path if staged else None)
            log_check(rec, lab, clouds, results, tcp, width)
            rec.flush()
            rec.disconnect()
    worst = {
        key: max((getattr(r, key) for r in results.values() if getattr(r, key) is not None), default=None)
        for key in ("cloud_to_cloud_mm", "fingertips_mm")
    }
    return {
        "lab": str(lab_path),
        "max_cloud_to_cloud_mm": worst["cloud_to_cloud_mm"],
        "max_fingertips_mm": worst["fingertips_mm"],
        "cameras": {n: r.summary() for n, r in results.items()},
        "tcp_xyz": [round(float(v), 4) for v in tcp[:3, 3]],
        "gripper_width": None if width is None or not np.isfinite(width) else round(float(width), 4),
        "tolerance_mm": settings.tolerance_mm,
        **({"rrd": str(settings.rrd)} if settings.rrd else {}),
    }


def beyond_tolerance(report: dict) -> bool:
    """Whether a ``run_calibration_check`` report's worst camera is beyond its tolerance."""
    worst = (report["max_cloud_to_cloud_mm"], report["max_fingertips_mm"])
    return any(v is not None and v > report["tolerance_mm"] for v in worst)
