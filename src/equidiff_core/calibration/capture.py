"""Collecting calibration samples: move the arm, let it settle, take every camera's colour image.

``capture_samples`` is the one loop for the lab and the twin; what differs is behind two
small interfaces: an *arm* (``move_to(T) -> (measured TCP, sim state or None)``) and a
*grab* function (sim state or None -> {camera: RGB image}).
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from ..robots.base import RobotState
from .board import BoardDetector, BoardSpec, CalibrationError
from .solve import CameraModel, Sample

Grab = Callable[[np.ndarray | None], dict[str, np.ndarray]]


def wait_at_rest(
    read_state: Callable[[], RobotState],
    settle_s: float,
    max_joint_step: float,
    timeout_s: float = 10.0,
    wall_timeout_s: float = 120.0,
) -> np.ndarray:
    """The TCP pose once no joint moved more than ``max_joint_step`` rad in ``settle_s``.

    Images and pose must show the same instant. Judged from joint positions, not the reported
    velocities: franky-sim reports a spurious joint-7 velocity (~0.08 rad/s) at rest.
    ``settle_s`` and ``timeout_s`` are the robot's own time (libfranka's state time): on the FR3
    that is the wall clock, while franky-sim on a loaded machine runs slower than real time, and
    a wall-clock timeout failed an arm that was still settling (CI). A robot whose clock stops
    (a lost connection) fails after ``wall_timeout_s`` of wall time.
    """
    wall_deadline = time.monotonic() + wall_timeout_s
    window = start = read_state()
    while True:
        time.sleep(settle_s / 5)
        state = read_state()
        if state.robot_time_s - window.robot_time_s >= settle_s:
            if np.abs(state.joint_positions - window.joint_positions).max() < max_joint_step:
                return state.ee_pose
            window = state
        if state.robot_time_s - start.robot_time_s > timeout_s or time.monotonic() > wall_deadline:
            raise CalibrationError(
                f"the arm did not come to rest within {timeout_s:.0f} s of robot time "
                f"({state.robot_time_s - start.robot_time_s:.1f} s passed)"
            )


class FrankyArm:
    """A robot behind ``robots.franky.FrankyRobot`` (an FR3, or franky-sim): blocking moves, O_T_EE read back.

    Moves use the backend's ``move_to`` (franky's CartesianMotion at the configured
    ``relative_dynamics_factor``, 0.15 by default), so the arm stays inside its speed limits.
    """

    def __init__(
        self, ip: str, realtime: bool = True, settle_s: float = 0.5, max_joint_step: float = 2e-4, gripper: bool = False
    ):
        from ..robots.franky import FrankyRobot

        self.settle_s = settle_s
        self.max_joint_step = max_joint_step
        self.robot = FrankyRobot(ip, realtime=realtime, gripper=gripper)
        self.robot.connect()

    def tcp_pose(self) -> np.ndarray:
        return self.robot.read_state().ee_pose

    def wait_at_rest(self, timeout_s: float = 10.0) -> np.ndarray:
        return wait_at_rest(self.robot.read_state, self.settle_s, self.max_joint_step, timeout_s)

    def move_to(self, T: np.ndarray) -> tuple[np.ndarray, None]:
        self.robot.move_to(T)
        return self.wait_at_rest(), None

    def close(self) -> None:
        self.robot.disconnect()


class RealSenseColour:
    """A RealSense's colour stream and its factory intrinsics, for board detection.

    The camera node's backend (``cameras.realsense``) yields clouds, not images; calibration
    needs the full-resolution colour image and its own intrinsics, so it opens the device
    itself (the camera node must not be running).
    """

    def __init__(self, camera, width: int = 1280, height: int = 720, fps: int = 30):
        import pyrealsense2 as rs

        self.name = camera.name
        self._pipe = rs.pipeline()
        cfg = rs.config()
        cfg.enable_device(str(camera.serial))
        cfg.enable_stream(rs.stream.color, width, height, rs.format.rgb8, fps)
        try:
            profile = self._pipe.start(cfg)
        except RuntimeError as err:
            raise CalibrationError(f"camera {camera.name} (serial {camera.serial}): {err}") from err
        intr = profile.get_stream(rs.stream.color).as_video_stream_profile().get_intrinsics()
        K = np.array([[intr.fx, 0, intr.ppx], [0, intr.fy, intr.ppy], [0, 0, 1.0]])
        # librealsense's colour model is Brown-Conrady with OpenCV's coefficient order
        self.model = CameraModel(camera.name, K, np.asarray(intr.coeffs[:5], dtype=np.float64), intr.width, intr.height)
        for _ in range(15):  # let auto exposure settle
            self._pipe.wait_for_frames()

    def grab(self) -> np.ndarray:
        frames = self._pipe.wait_for_frames()
        for _ in range(2):  # drop frames buffered while the arm moved
            frames = self._pipe.wait_for_frames()
        return np.asanyarray(frames.get_color_frame().get_data()).copy()

    def close(self) -> None:
        self._pipe.stop()


def capture_samples(
    arm, poses: list[np.ndarray], grab: Grab, spec: BoardSpec, log=print, images: dict | None = None
) -> list[Sample]:
    """Visit ``poses``; at each, detect the board in every camera's image. ``images`` collects them if given."""
    detector = BoardDetector(spec)
    samples = []
    for k, T in enumerate(poses):
        measured, state = arm.move_to(T)
        dets = {}
        frames = grab(state)
        for name, rgb in frames.items():
            det = detector.detect(rgb)
            if det is not None:
                dets[name] = det
            if images is not None:
                images.setdefault(name, []).append(rgb)
        log(
            f"pose {k + 1}/{len(poses)}: board corners "
            + ", ".join(f"{name} {len(dets[name]) if name in dets else 0}" for name in frames)
        )
        samples.append(Sample(measured, dets))
    return samples
