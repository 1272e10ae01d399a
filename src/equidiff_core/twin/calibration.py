"""Calibration in the digital twin: the board on the twin's hand, the arm moved, the cameras rendered.

The twin's cameras stand where lab.yaml says: that is the ground truth the calibration must
recover. The calibration itself only gets perturbed guesses (as a lab's hand-typed numbers
would be) to plan the poses, and solves from the images and the robot's TCP poses with the
same code as on hardware.

Two ways to move the arm, one solver:

* ``FrankyTwinArm`` (``equidiff calibrate cameras --twin``): the lab's path. franky connects to
  franky-sim (``twin.sim.TwinSim``, real-time loop, in a process of its own) and franka_node's
  control loop moves it (``capture.FrankyArm``: safety box, cone, speed limits); the TCP pose is
  what libfranka reports (O_T_EE); the cameras render the state the sim shares.
* ``DirectSimArm`` (the CI test): the same scene stepped in-process (``twin.sim.DirectSim``),
  TCP read from MuJoCo; no server, no real-time clock, so it fits a test's time budget. It
  drives the arm by DirectSim's IK, not by franka_node's control loop; the poses it visits are
  checked against the same limits (``capture_samples``).
"""

from __future__ import annotations

import functools
import math
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from PIL import Image
from scipy.spatial.transform import Rotation

from ..calibration.board import BoardSpec, CalibrationError
from ..calibration.capture import FrankyArm, capture_samples
from ..calibration.limits import MotionLimits
from ..calibration.plan import PlanConfig, plan_poses
from ..calibration.solve import Calibration, CameraModel, calibrate, pose_error
from ..cameras.twin import Intrinsics, TwinCamera
from ..config import Extrinsics, LabConfig, dump_yaml, to_dict
from ..geometry import make_pose
from ..robots.franky.hand import TCP_OFFSET
from ..robots.franky.sim import SimServer
from .config import BoardMountConfig
from .scene import build_model
from .shared_state import StateReader
from .sim import DirectSim


def nominal_mount(spec: BoardSpec, offset_x: float = 0.06, height: float = 0.0434) -> np.ndarray:
    """T_tcp_board of the recommended mount (m, TCP frame: z along the fingers).

    The printed side faces back up the fingers (board z = TCP z), so with the gripper pointing
    down it faces up; the board sits beside the hand (its edge ``offset_x`` from the TCP axis,
    centred across the fingers), ``height`` above the TCP. On a real robot this is only the
    planner's first guess: the solver finds the true mount.
    """
    return make_pose(np.eye(3), np.array([offset_x, -spec.size_m[1] / 2, -height]))


def twin_camera_model(cam, render) -> CameraModel:
    """A twin camera's intrinsics in OpenCV's convention (MuJoCo's pixel centres are at +0.5)."""

    intr = Intrinsics.from_fovy(render.width, render.height, render.fovy_deg)
    K = np.array([[intr.fx, 0, intr.cx - 0.5], [0, intr.fy, intr.cy - 0.5], [0, 0, 1.0]])
    return CameraModel(cam.name, K, np.zeros(5), intr.width, intr.height)


def twin_config_with_board(
    twin_cfg, spec: BoardSpec, T_tcp_board: np.ndarray, texture_dir: str | Path, width: int = 1280, height: int = 720
):
    """The twin config with the board on the hand and noise-free colour at ``width`` x ``height``.

    The hand body sits ``TCP_OFFSET`` behind the TCP (same rotation), so the mount moves by it.
    """

    texture = Path(texture_dir) / f"charuco_{spec.squares_x}x{spec.squares_y}_{spec.dictionary}.png"
    texture.parent.mkdir(parents=True, exist_ok=True)

    Image.fromarray(spec.image(200)).save(texture)
    T_hand_board = make_pose(np.eye(3), TCP_OFFSET) @ T_tcp_board
    q = Rotation.from_matrix(T_hand_board[:3, :3]).as_quat()  # xyzw
    mount = BoardMountConfig(
        str(texture),
        spec.size_m,
        tuple(map(float, T_hand_board[:3, 3])),
        (float(q[3]), float(q[0]), float(q[1]), float(q[2])),
    )
    render = replace(twin_cfg.render, width=width, height=height, depth_noise=False, dropout=0.0)
    return replace(twin_cfg, scene=replace(twin_cfg.scene, calibration_board=mount), render=render)


def perturb_lab(lab: LabConfig, translation_m: float, rotation_deg: float, seed: int) -> LabConfig:
    """The lab with every camera moved by exactly ``translation_m`` and turned by ``rotation_deg``
    in random directions: a hand-typed guess to start from."""
    rng = np.random.default_rng(seed)
    cams = []
    for cam in lab.cameras:
        d = rng.normal(size=3)
        axis = rng.normal(size=3)
        delta = make_pose(
            Rotation.from_rotvec(axis / np.linalg.norm(axis) * math.radians(rotation_deg)).as_matrix(),
            d / np.linalg.norm(d) * translation_m,
        )
        cams.append(replace(cam, extrinsics=Extrinsics.from_matrix(cam.extrinsics.matrix() @ delta)))
    return replace(lab, cameras=tuple(cams))


class DirectSimArm:
    """The twin scene in-process: the arm is driven to each pose by DirectSim's controller."""

    def __init__(self, twin_cfg, settle_ms: int = 1500, tolerance_m: float = 0.005, gripper_width: float = 0.08):
        self.gripper_width = gripper_width
        self.sim = DirectSim(twin_cfg)
        self.sim.reset(0)
        self.settle_ms = settle_ms
        self.tolerance_m = tolerance_m

    @property
    def model(self):
        """The scene's MuJoCo model (for reading ``qpos``)."""
        return self.sim.model

    def tcp_pose(self) -> np.ndarray:
        return self.sim.tcp_pose()

    def move_to(self, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Go to ``T`` and come to rest; (measured TCP pose, qpos) there."""
        steps = 100
        for _ in range(self.settle_ms // steps):
            self.sim.command(
                T, self.gripper_width
            )  # IK again from where the arm got to (DirectSim's IK iterates 8 times)
            self.sim.step(steps)
        measured = self.sim.tcp_pose()
        if np.linalg.norm(measured[:3, 3] - T[:3, 3]) > self.tolerance_m:
            raise CalibrationError(
                f"the arm did not reach {np.round(T[:3, 3], 3)} (stopped at "
                f"{np.round(measured[:3, 3], 3)}): unreachable pose"
            )
        return measured, self.sim.data.qpos.copy()

    def close(self) -> None:
        self.sim.close()


class FrankyTwinArm:
    """franky against franky-sim (the twin's libfranka server, real-time loop), as on the lab's FR3.

    The sim runs in a process of its own (``python -m equidiff_core.twin.sim``), as an FR3's
    controller does: a sim thread in this process waited for its GIL behind rendering and
    detection, and on a loaded machine fell silent past libfranka's 1 s receive timeout.
    """

    def __init__(self, twin_cfg, limits: MotionLimits):
        self.twin_cfg = twin_cfg
        self._dir = tempfile.TemporaryDirectory(prefix="equidiff_calib_twin_")
        config = Path(self._dir.name) / "twin.yaml"
        config.write_text(dump_yaml(to_dict(twin_cfg)))
        shm_name = f"equidiff_calib_{time.time_ns()}"
        self.twin = SimServer(module="equidiff_core.twin.sim", args=("--config", str(config), "--shm", shm_name))
        self.reader = None
        try:
            self.twin.start()
            shared, nq = self.twin.ready  # READY <host> <shm name> <nq>
            self.reader = StateReader(shared, nq=int(nq))
            self.arm = FrankyArm(self.twin.host, limits, realtime=False)
        except Exception:
            if self.reader is not None:
                self.reader.close()
            self.twin.stop()
            self._dir.cleanup()
            raise

    @functools.cached_property
    def model(self):
        """The scene's MuJoCo model (the server's own layout of ``qpos``), built here on demand."""
        return build_model(self.twin_cfg)

    def tcp_pose(self) -> np.ndarray:
        return self.arm.tcp_pose()

    def move_to(self, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        measured, _ = self.arm.move_to(T)
        qpos, _, _ = self.reader.read()  # the state the sim shares with its cameras, taken at rest
        return measured, qpos

    def close(self) -> None:
        try:
            self.arm.close()
        finally:
            self.reader.close()
            self.twin.stop()
            self._dir.cleanup()


class TwinCameras:
    """The twin's cameras at their true poses, rendering a given sim state (colour only is used)."""

    def __init__(self, lab_truth: LabConfig, twin_cfg):
        self.cams = [
            TwinCamera(cam, state_source=lambda t: (None, 0.0, 0), paced=False, twin_config=twin_cfg)
            for cam in lab_truth.cameras
        ]
        for cam in self.cams:
            cam.connect()

    def grab(self, qpos: np.ndarray) -> dict[str, np.ndarray]:
        return {cam.camera.name: cam.render(qpos)[0] for cam in self.cams}

    def close(self) -> None:
        for cam in self.cams:
            cam.disconnect()


def errors_against_truth(result, lab_truth: LabConfig) -> dict[str, dict]:

    out = {}
    for cam in lab_truth.cameras:
        t_mm, r_deg = pose_error(result.cameras[cam.name].T_base_cam, cam.extrinsics.matrix())
        out[cam.name] = {"translation_error_mm": round(t_mm, 3), "rotation_error_deg": round(r_deg, 4)}
    return out


def calibrate_twin(
    lab_truth: LabConfig,
    twin_cfg,
    spec: BoardSpec,
    plan: PlanConfig,
    arm: str = "franky",
    perturb_m: float = 0.03,
    perturb_deg: float = 3.0,
    texture_dir: str | Path | None = None,
    log=print,
    limits: MotionLimits | None = None,
) -> tuple[dict, Calibration, LabConfig]:
    """The whole calibration in the twin from perturbed guesses; (report, calibration, the guessed lab).

    ``arm``: "franky" (franky against franky-sim, the lab's path) or "direct" (in-process sim).
    ``limits``: default lab.yaml's safety box and the project's control.yaml.
    """
    limits = limits or MotionLimits.load(lab_truth)

    guess = perturb_lab(lab_truth, perturb_m, perturb_deg, plan.seed)
    mount = nominal_mount(spec)
    with tempfile.TemporaryDirectory(prefix="equidiff_board_") as tmp:
        cfg = twin_config_with_board(twin_cfg, spec, mount, texture_dir or tmp)
        models = [twin_camera_model(cam, cfg.render) for cam in lab_truth.cameras]
        start = time.monotonic()
        cams = TwinCameras(lab_truth, cfg)
        try:
            mover = FrankyTwinArm(cfg, limits) if arm == "franky" else DirectSimArm(cfg)
            try:
                poses = plan_poses(guess, models, spec, mount, plan, start=mover.tcp_pose(), limits=limits)
                samples = capture_samples(mover, poses, cams.grab, spec, limits, log=log)
            finally:
                mover.close()
        finally:
            cams.close()
    result = calibrate(spec, models, samples)
    errors = errors_against_truth(result, lab_truth)
    report = {
        "max_translation_error_mm": max(e["translation_error_mm"] for e in errors.values()),
        "max_rotation_error_deg": max(e["rotation_error_deg"] for e in errors.values()),
        "cameras": {name: {**errors[name], **result.cameras[name].summary()} for name in errors},
        "initial_guess_error": {"translation_mm": round(perturb_m * 1000, 3), "rotation_deg": perturb_deg},
        "poses": len(samples),
        "arm": "franky+franky-sim" if arm == "franky" else "in-process MuJoCo",
        "image": f"{cfg.render.width}x{cfg.render.height}",
        "wall_s": round(time.monotonic() - start, 1),
    }
    return report, result, guess
