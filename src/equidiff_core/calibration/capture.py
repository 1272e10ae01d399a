"""Collecting calibration samples: move the arm, let it settle, take every camera's colour image.

``capture_samples`` is the one loop for the lab and the twin; what differs is behind two
small interfaces: an *arm* (``move_to(T) -> (measured TCP, sim state or None)``) and a
*grab* function (sim state or None -> {camera: RGB image}). On a robot the arm is
``ControlledArm``: franka_node's control loop with its safety box, cone and speed limits.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from .. import geometry
from ..control.controller import Controller
from ..robots.base import Robot, RobotError, RobotState
from ..robots.franky import FrankyRobot
from ..wire.chunk import PoseChunk
from .board import BoardDetector, BoardSpec, CalibrationError
from .limits import MotionLimits
from .solve import CameraModel, Sample

Grab = Callable[[np.ndarray | None], dict[str, np.ndarray]]


def wait_at_rest(
    read_state: Callable[[], RobotState],
    settle_s: float,
    max_step_m: float = 1e-4,
    max_step_rad: float = 2e-4,
    timeout_s: float = 10.0,
    wall_timeout_s: float = 120.0,
) -> np.ndarray:
    """The TCP pose once it moved less than ``max_step_m`` and turned less than ``max_step_rad`` in ``settle_s``.

    Images and pose must show the same instant, and the board is on the hand: the TCP is what
    must stand still. Not the joints: under franka_node's Cartesian impedance control the elbow
    keeps drifting in the null space with the hand still (franky-sim: joints 1 and 3 turning
    ~0.6 mrad/s in opposite directions, on and on), and franky-sim reports a spurious joint-7
    velocity (~0.08 rad/s) at rest. ``settle_s`` and ``timeout_s`` are the robot's own time
    (libfranka's state time): on the FR3 that is the wall clock, while franky-sim on a loaded
    machine runs slower than real time, and a wall-clock timeout failed an arm that was still
    settling (CI). A robot whose clock stops (a lost connection) fails after ``wall_timeout_s``
    of wall time. A backend without a clock of its own (the dry run) is judged on the states'
    read times.
    """

    def clock(state: RobotState) -> float:
        return state.robot_time_s if np.isfinite(state.robot_time_s) else state.stamp_ns / 1e9

    wall_deadline = time.monotonic() + wall_timeout_s
    window = start = read_state()
    while True:
        time.sleep(settle_s / 5)
        state = read_state()
        if clock(state) - clock(window) >= settle_s:
            a, b = window.ee_pose, state.ee_pose
            if (
                np.linalg.norm(b[:3, 3] - a[:3, 3]) < max_step_m
                and geometry.rotation_angle(a[:3, :3], b[:3, :3]) < max_step_rad
            ):
                return b
            window = state
        if clock(state) - clock(start) > timeout_s:
            raise CalibrationError(f"the arm did not come to rest within {timeout_s:.0f} s of robot time")
        if time.monotonic() > wall_deadline:
            raise CalibrationError(
                f"the arm did not come to rest: only {clock(state) - clock(start):.1f} s of robot time passed in "
                f"{wall_timeout_s:.1f} s (is the robot's state still coming? a lost connection stops its clock)"
            )


def glide_chunk(
    start: np.ndarray,
    goal: np.ndarray,
    now_ns: int,
    speed_m_s: float,
    angular_speed_rad_s: float,
    hold_s: float,
    width: float,
) -> PoseChunk:
    """From ``start`` to ``goal`` in a straight line and one turn, at most at the given speeds, in
    steps of at most 0.1 s, 1 cm and 0.05 rad (the control loop interpolates between them and
    checks the first one against the arm's pose), then ``goal`` held for ``hold_s`` (franka_node's
    watchdog counts from a chunk's last step). The gripper is kept at ``width``."""
    distance = float(np.linalg.norm(goal[:3, 3] - start[:3, 3]))
    angle = geometry.rotation_angle(start[:3, :3], goal[:3, :3])
    duration = max(distance / speed_m_s, angle / angular_speed_rad_s, 0.2)
    s = np.linspace(0.0, 1.0, int(np.ceil(max(duration / 0.1, distance / 0.01, angle / 0.05))) + 1)
    turns = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([start[:3, :3], goal[:3, :3]])))(s).as_matrix()
    poses = [geometry.make_pose(R, (1 - a) * start[:3, 3] + a * goal[:3, 3]) for a, R in zip(s, turns)]
    times = now_ns + (np.append(s * duration, duration + hold_s) * 1e9).astype(np.int64)
    return PoseChunk(now_ns, times, np.stack([*poses, goal]), np.full(len(times), width))


class ControlledArm:
    """A robot backend (``robots.base.Robot``, connected) moved by franka_node's control loop.

    ``control.Controller`` runs in a thread of this process, as in franka_node: every command
    is clipped to the safety box, kept in the orientation cone and speed-limited; a robot error,
    the arm diverging from its command or a joint running into its limit stops it, and then
    calibration fails with the reason (an operator looks at the arm; nothing resumes on its
    own). ``start`` (on the first move) first takes the arm to control.yaml's home pose when
    ``home_on_start`` is set, as franka_node does; otherwise the TCP must already be inside the
    box and the cone. ``move_to`` glides to a pose (checked against ``limits`` first) and returns
    the measured TCP once the arm has come to rest.
    """

    def __init__(
        self,
        robot: Robot,
        limits: MotionLimits,
        speed_m_s: float = 0.1,
        angular_speed_rad_s: float = 0.4,
        settle_s: float = 0.5,
        move_timeout_s: float = 120.0,
    ):
        self.robot, self.limits = robot, limits
        self.speed_m_s, self.angular_speed_rad_s = speed_m_s, angular_speed_rad_s
        self.settle_s, self.move_timeout_s = settle_s, move_timeout_s
        self.controller = Controller(robot, limits.box, limits.control)
        self.started = False

    def start(self) -> None:
        """Start the control loop (homing first if control.yaml says so); idempotent."""
        if self.started:
            return
        try:
            self.controller.start()
        except (RobotError, ValueError) as err:
            raise CalibrationError(f"cannot start franka_node's control loop for calibration: {err}") from err
        self.started = True

    def tcp_pose(self) -> np.ndarray:
        state = self.controller.state if self.started else None
        return (state or self.robot.read_state()).ee_pose

    def read_state(self) -> RobotState:
        """The robot state the control loop read last (the robot's own when it is not running)."""
        return (self.controller.state if self.started else None) or self.robot.read_state()

    def stopped_reason(self) -> str:
        """Why the control loop holds the arm ('' while it follows commands)."""
        stats = self.controller.stats
        if self.controller.faulted:
            return f"faulted after repeated failures ({stats.last_recovery_reason or stats.last_divergence})"
        return self.controller.awaiting_ack

    def _raise_if_stopped(self) -> None:
        if reason := self.stopped_reason():
            raise CalibrationError(
                f"the control loop stopped the arm: {reason}; calibration aborted (look at the arm, then start again)"
            )

    def offer(self, chunk: PoseChunk) -> bool:
        """Hand a chunk to the control loop; False if it refused it (the arm holds), CalibrationError
        if the loop has stopped the arm."""
        self._raise_if_stopped()
        return self.controller.submit(chunk)

    def submit(self, chunk: PoseChunk) -> None:
        """Hand a chunk to the control loop; CalibrationError if it refuses it."""
        if not self.offer(chunk):
            raise CalibrationError(f"the control loop refused the motion: {self.controller.stats.last_rejection}")

    def glide(self, T: np.ndarray) -> PoseChunk:
        """The glide from the current command to ``T`` (checked against ``limits``), ``T`` then held
        for 5 min, until the next move replaces it: after a chunk's last step franka_node's watchdog
        holds wherever the arm *is*, which a still settling arm would carry into the capture, and on
        a busy machine a glide plus a capture took over 30 s."""
        command = self.controller.last_command
        here = command.target.pose if command is not None else self.tcp_pose()
        self.limits.check([T], start=here)
        width = self.read_state().gripper_width  # left as it is (NaN without a gripper: the hand's open width)
        width = width if np.isfinite(width) else self.limits.control.safety.max_gripper_width_m
        now = self.controller.clock.now_ns()
        return glide_chunk(here, T, now, self.speed_m_s, self.angular_speed_rad_s, 300.0, width)

    def move_to(self, T: np.ndarray) -> tuple[np.ndarray, None]:
        """Glide to ``T`` through the control loop; the measured TCP once the arm rests there."""
        self.start()
        chunk = self.glide(T)
        now = chunk.stamp_ns
        self.submit(chunk)
        # Arrived when the loop's own command has reached the goal (on a sim slower than real time
        # the speed limits, applied in robot time, make that later than the chunk says).
        deadline = time.monotonic() + self.move_timeout_s
        while True:
            self._raise_if_stopped()
            command = self.controller.last_command
            if command is not None and command.stamp_ns > now:
                pose = command.target.pose
                if (
                    np.linalg.norm(pose[:3, 3] - T[:3, 3]) < 1e-4
                    and geometry.rotation_angle(pose[:3, :3], T[:3, :3]) < 1e-3
                ):
                    break
            if time.monotonic() > deadline:
                raise CalibrationError(
                    f"the arm did not reach {np.round(T[:3, 3], 3).tolist()} within {self.move_timeout_s:.0f} s"
                )
            time.sleep(0.02)
        return self.wait_at_rest(), None

    def wait_at_rest(self, timeout_s: float = 10.0) -> np.ndarray:
        self._raise_if_stopped()
        pose = wait_at_rest(self.read_state, self.settle_s, timeout_s=timeout_s)
        self._raise_if_stopped()
        return pose

    def close(self) -> None:
        try:
            if self.started:
                self.controller.stop()
        finally:
            self.robot.disconnect()


class FrankyArm(ControlledArm):
    """An FR3 (or franky-sim) through ``robots.franky.FrankyRobot``, with control.yaml's franky
    settings and limits, moved by franka_node's control loop (no gripper: the board is on the hand)."""

    def __init__(self, ip: str, limits: MotionLimits, realtime: bool = True, **kwargs):
        robot = FrankyRobot(
            ip, config=limits.control.franky, safety=limits.control.safety, realtime=realtime, gripper=False
        )
        robot.connect()
        super().__init__(robot, limits, **kwargs)


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
    arm,
    poses: list[np.ndarray],
    grab: Grab,
    spec: BoardSpec,
    limits: MotionLimits,
    log=print,
    images: dict | None = None,
) -> list[Sample]:
    """Visit ``poses``; at each, detect the board in every camera's image. ``images`` collects them if given.

    The whole plan is checked against ``limits`` before the first move."""
    limits.check(poses)
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
