"""SpaceMouse teleoperation: a 6-D twist + buttons -> an absolute TCP target and gripper width.

``TeleopIntegrator`` is the whole behaviour, without ROS or a device, so the twin's scripted
expert and the tests drive exactly what the node runs:

* deadzone on the normalised axes (re-scaled so the output starts at 0 at the deadzone edge),
  then per-axis scaling to m/s and rad/s at full deflection;
* translation in the base frame or the tool frame; rotation about the TCP, with its axes in
  the base or the tool frame; an optional rotation lock (translation only);
* integration from the robot's **measured** pose (``reset``), the target kept inside the
  workspace box and at most ``max_lead_m`` / ``max_lead_rad`` ahead of the measured pose
  (a blocked arm does not wind the target up);
* two gripper buttons: ``buttons`` (left opens, right closes), ``toggle`` (either toggles) or
  ``hold`` (closed while the close button is held);
* an optional clutch button (no motion unless it is held) and an optional rotation-enable
  button (translation only unless it is held);
* stale input counts as no input (hold): every ``TeleopInput`` carries the time the device
  last *reported* (the Joy header stamp; the last HID report for the direct backend), so a
  device, driver or cable that stops reporting stops the motion ``input_timeout_s`` later.

Input sources (``spacemouse``: the device via pyspacemouse/hidapi, polled by the node at
``rate_hz``; ``joy``: ``sensor_msgs/Joy`` from the spacenav driver) both produce ``TeleopInput``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Self

import numpy as np
from scipy.spatial.transform import Rotation

from .. import geometry
from ..config import Workspace, bounded, described
from ..control.config import HAND_MAX_WIDTH_M
from ..wire.chunk import PoseChunk
from ..wire.rosmsg import NS_PER_S, stamp_to_ns


class TeleopError(RuntimeError):
    """No input device, or an input that cannot be used."""


SOURCES = ("joy", "spacemouse")
FRAMES = ("base", "tool")
GRIPPER_MODES = ("buttons", "toggle", "hold")


@dataclass(frozen=True)
class TeleopConfig:
    """How teleop_node turns the SpaceMouse into commands (config/data.yaml ``teleop_node``); each field is
    one of its ROS parameters, described here once."""

    source: str = described("joy", "Input: sensor_msgs/Joy on /spacenav/joy, or the SpaceMouse by direct HID", SOURCES)
    device: str = described("", "pyspacemouse device name; empty: the first supported one found")
    # diffusion_policy polls its SpaceMouse at 200 Hz; a SpaceMouse needs >= 100 Hz (__post_init__)
    rate_hz: float = bounded(200.0, unit="Hz", gt=0, le=1000, description="Device polling and integration rate")
    publish_hz: float = bounded(20.0, unit="Hz", gt=0, le=1000, description="/franka/command_chunk rate")
    command_lead_s: float = bounded(
        0.05, unit="s", ge=0, le=1, description="Each target's time_from_start: reached this long after publishing"
    )
    deadzone: float = bounded(0.08, unit="", ge=0, lt=1, description="Deadzone, as a fraction of the axis range")
    linear_scale: tuple[float, float, float] = bounded(
        (0.15, 0.15, 0.15), unit="m/s", ge=0, description="Translation speed at full deflection, x y z"
    )
    angular_scale: tuple[float, float, float] = bounded(
        (0.8, 0.8, 0.8), unit="rad/s", ge=0, description="Rotation speed at full deflection, roll pitch yaw"
    )
    axis_signs: tuple[float, float, float, float, float, float] = described(
        (1, 1, 1, 1, 1, 1), "Sign of each axis x y z roll pitch yaw, for how the device is mounted"
    )
    translation_frame: str = described("base", "Frame of the translation axes", FRAMES)
    rotation_frame: str = described("base", "Axes of the rotation about the TCP", FRAMES)
    lock_rotation: bool = described(False, "Translate only; the orientation holds")
    gripper_mode: str = described(
        "buttons",
        "buttons: open_button opens, close_button closes; toggle: either toggles; hold: closed while held",
        GRIPPER_MODES,
    )
    open_button: int = bounded(0, unit="", ge=0, description="Index of the button that opens the gripper")
    close_button: int = bounded(1, unit="", ge=0, description="Index of the button that closes the gripper")
    open_width: float = bounded(0.08, unit="m", ge=0, le=HAND_MAX_WIDTH_M, description="Gripper width when open")
    # franky grasps with a force: the width is the goal, not where the fingers stop
    closed_width: float = bounded(
        0.0, unit="m", ge=0, le=HAND_MAX_WIDTH_M, description="Gripper width commanded to close"
    )
    workspace_margin: float = bounded(
        0.0, unit="m", ge=0, le=0.5, description="Distance the target keeps from the workspace box faces"
    )
    max_lead_m: float = bounded(
        0.05, unit="m", gt=0, le=0.5, description="How far the target may run ahead of the measured TCP"
    )
    max_lead_rad: float = bounded(
        0.5, unit="rad", gt=0, le=math.pi, description="How far the target may turn ahead of the measured TCP"
    )
    input_timeout_s: float = bounded(
        0.2, unit="s", gt=0, le=1, description="Input older than this is no input: the target holds"
    )
    clutch_button: int = bounded(
        -1, unit="", ge=-1, description="Button that must be held for any motion; -1: no clutch"
    )
    rotation_button: int = bounded(
        -1, unit="", ge=-1, description="Button that must be held to rotate; -1: always rotate"
    )

    def __post_init__(self):
        if self.source not in SOURCES:
            raise ValueError(f"source must be 'joy' or 'spacemouse', got {self.source!r}")
        if self.translation_frame not in FRAMES or self.rotation_frame not in FRAMES:
            raise ValueError("translation_frame and rotation_frame must be 'base' or 'tool'")
        if self.gripper_mode not in GRIPPER_MODES:
            raise ValueError(f"gripper_mode must be buttons/toggle/hold, got {self.gripper_mode!r}")
        if not 0 <= self.deadzone < 1:
            raise ValueError(f"deadzone must be in [0, 1), got {self.deadzone}")
        if self.rate_hz < 100 and self.source == "spacemouse":
            raise ValueError(f"a SpaceMouse must be polled at >= 100 Hz, got rate_hz={self.rate_hz}")
        if self.publish_hz <= 0 or self.rate_hz <= 0:
            raise ValueError("rate_hz and publish_hz must be positive")
        if not 0 < self.input_timeout_s <= 1.0:
            raise ValueError(f"input_timeout_s must be in (0, 1] s, got {self.input_timeout_s}")
        gripper = {self.open_button, self.close_button}
        for name in ("clutch_button", "rotation_button"):
            button = getattr(self, name)
            if button < -1:
                raise ValueError(f"{name} must be a button index or -1 (off), got {button}")
            if button in gripper:
                raise ValueError(
                    f"{name} {button} is also a gripper button (open_button {self.open_button}, "
                    f"close_button {self.close_button}); pick another button"
                )
        if self.clutch_button >= 0 and self.clutch_button == self.rotation_button:
            raise ValueError(f"clutch_button and rotation_button are both {self.clutch_button}")


@dataclass(frozen=True)
class TeleopInput:
    """One device sample: axes [x, y, z, roll, pitch, yaw] normalised to [-1, 1], buttons 0/1.

    ``stamp_ns``: when the device reported this state, on the consumer's clock (0 = never).
    """

    axes: tuple[float, ...]
    buttons: tuple[int, ...] = ()
    stamp_ns: int = 0

    @classmethod
    def from_joy(cls, msg) -> TeleopInput:
        """sensor_msgs/Joy in the spacenav layout (either message flavour)."""
        axes = [float(a) for a in msg.axes]
        if len(axes) < 6:
            raise TeleopError(f"Joy message has {len(axes)} axes; the spacenav layout has 6 (x y z roll pitch yaw)")
        if not np.all(np.isfinite(axes)):
            raise TeleopError("Joy axes contain NaN or inf")
        return cls(tuple(axes[:6]), tuple(int(b) for b in msg.buttons), stamp_to_ns(msg.header.stamp))


def apply_deadzone(axes: np.ndarray, deadzone: float) -> np.ndarray:
    """Zero inside the deadzone, linear from 0 at its edge to +-1 at full deflection."""
    a = np.clip(np.asarray(axes, dtype=np.float64), -1.0, 1.0)
    mag = np.maximum(np.abs(a) - deadzone, 0.0) / (1.0 - deadzone)
    return np.sign(a) * mag


@dataclass
class TeleopIntegrator:
    """Integrates twists into an absolute target; ``reset`` with the measured pose before use."""

    config: TeleopConfig
    workspace: Workspace
    target: np.ndarray | None = None  # (4, 4)
    width: float = float("nan")
    measured: np.ndarray | None = None
    _prev_buttons: tuple[int, ...] = field(default=(), repr=False)
    _closed: bool = False

    @property
    def ready(self) -> bool:
        return self.target is not None

    def reset(self, measured_pose: np.ndarray, measured_width: float | None = None) -> None:
        """Start (again) from the robot's measured pose; the gripper state follows its width."""
        pose = geometry.validate_pose(np.asarray(measured_pose, dtype=np.float64))
        self.measured = pose.copy()
        self.target = pose.copy()
        self.target[:3, 3] = self._clamp_box(pose[:3, 3])
        if measured_width is not None and np.isfinite(measured_width):
            self._closed = measured_width < 0.5 * (self.config.open_width + self.config.closed_width)
        self.width = self.config.closed_width if self._closed else self.config.open_width

    def observe(self, measured_pose: np.ndarray) -> None:
        """Latest measured TCP pose (bounds how far the target may lead)."""
        self.measured = geometry.validate_pose(np.asarray(measured_pose, dtype=np.float64)).copy()

    def twist(self, axes: Sequence[float], buttons: Sequence[int] = ()) -> tuple[np.ndarray, np.ndarray]:
        """Normalised axes (+ the clutch / rotation-enable buttons) -> (linear m/s, angular rad/s),
        still in the device's frame convention."""
        cfg = self.config
        a = np.asarray(axes, dtype=np.float64)[:6] * np.asarray(cfg.axis_signs, dtype=np.float64)
        if a.shape != (6,) or not np.all(np.isfinite(a)):
            raise TeleopError(f"expected 6 finite axes, got {axes!r}")
        a = apply_deadzone(a, cfg.deadzone)
        if cfg.clutch_button >= 0 and not _pressed(buttons, cfg.clutch_button):
            return np.zeros(3), np.zeros(3)
        v = a[:3] * np.asarray(cfg.linear_scale)
        rotate = not cfg.lock_rotation and (cfg.rotation_button < 0 or _pressed(buttons, cfg.rotation_button))
        w = a[3:] * np.asarray(cfg.angular_scale) if rotate else np.zeros(3)
        return v, w

    def engaged(self, inp: TeleopInput | None) -> bool:
        """The operator is driving: a twist beyond the deadzone (clutch held, if any), or a
        gripper button held or just released (``hold`` mode opens on release)."""
        if inp is None:
            return False
        v, w = self.twist(inp.axes, inp.buttons)
        if np.any(v) or np.any(w):
            return True
        grip = (self.config.open_button, self.config.close_button)
        return any(_pressed(inp.buttons, b) or _pressed(self._prev_buttons, b) for b in grip)

    def step(self, inp: TeleopInput | None, dt: float) -> tuple[np.ndarray, float]:
        """Advance by ``dt`` seconds with input ``inp`` (None = no fresh input: hold); returns (target, width)."""
        if self.target is None:
            raise TeleopError("teleop has no start pose yet: reset() with the measured TCP pose first")
        if dt < 0 or not np.isfinite(dt):
            raise TeleopError(f"bad time step {dt}")
        if inp is None:
            return self.target.copy(), self.width
        v, w = self.twist(inp.axes, inp.buttons)
        R = self.target[:3, :3]
        p = self.target[:3, 3]
        dp = (R @ v if self.config.translation_frame == "tool" else v) * dt
        dR = Rotation.from_rotvec(w * dt).as_matrix()
        R_new = R @ dR if self.config.rotation_frame == "tool" else dR @ R
        p_new = self._limit_lead(self._clamp_box(p + dp))
        R_new = self._limit_rot_lead(_orthonormalise(R_new))
        self.target = geometry.make_pose(R_new, p_new)
        self._buttons(tuple(inp.buttons))
        return self.target.copy(), self.width

    def chunk(self, now_ns: int) -> PoseChunk:
        """The current target as a one-point chunk (stamp = now, reached ``command_lead_s`` later)."""
        if self.target is None:
            raise TeleopError("teleop has no target yet")
        t = now_ns + int(self.config.command_lead_s * NS_PER_S)
        return PoseChunk(
            int(now_ns),
            np.array([t], dtype=np.int64),
            self.target[None].copy(),
            np.array([self.width], dtype=np.float64),
        )

    # -- helpers ---------------------------------------------------------------------------
    def _clamp_box(self, p: np.ndarray) -> np.ndarray:
        m = self.config.workspace_margin
        return np.clip(p, self.workspace.lower + m, self.workspace.upper - m)

    def _limit_lead(self, p: np.ndarray) -> np.ndarray:
        if self.measured is None or self.config.max_lead_m <= 0:
            return p
        q = self.measured[:3, 3]
        d = p - q
        n = float(np.linalg.norm(d))
        if n > self.config.max_lead_m:
            p = self._clamp_box(q + d * (self.config.max_lead_m / n))
        return p

    def _limit_rot_lead(self, R: np.ndarray) -> np.ndarray:
        if self.measured is None or self.config.max_lead_rad <= 0:
            return R
        Rm = self.measured[:3, :3]
        rel = Rotation.from_matrix(Rm.T @ R).as_rotvec()
        ang = float(np.linalg.norm(rel))
        if ang > self.config.max_lead_rad:
            R = Rm @ Rotation.from_rotvec(rel * (self.config.max_lead_rad / ang)).as_matrix()
        return R

    def _buttons(self, buttons: tuple[int, ...]) -> None:
        cfg = self.config

        def rising(i: int) -> bool:
            return _pressed(buttons, i) and not _pressed(self._prev_buttons, i)

        if cfg.gripper_mode == "buttons":
            if rising(cfg.close_button):
                self._closed = True
            elif rising(cfg.open_button):
                self._closed = False
        elif cfg.gripper_mode == "toggle":
            if rising(cfg.open_button) or rising(cfg.close_button):
                self._closed = not self._closed
        else:  # hold
            self._closed = _pressed(buttons, cfg.close_button)
        self._prev_buttons = buttons
        self.width = cfg.closed_width if self._closed else cfg.open_width


def _pressed(buttons: Sequence[int], index: int) -> bool:
    return 0 <= index < len(buttons) and bool(buttons[index])


def _orthonormalise(R: np.ndarray) -> np.ndarray:
    """Re-project onto SO(3): thousands of small integration steps must not drift off it."""
    u, _, vt = np.linalg.svd(R)
    Rn = u @ vt
    if np.linalg.det(Rn) < 0:
        u[:, -1] *= -1
        Rn = u @ vt
    return Rn


# --- input sources ----------------------------------------------------------------------------


class SpaceMouseSource:
    """A 3Dconnexion SpaceMouse read directly over HID with pyspacemouse (ROS axis convention).

    ``read(now_ns)`` is non-blocking and returns the latest state, stamped with when the device
    last reported (pyspacemouse times each HID report it processes), so a device that stops
    reporting goes stale instead of repeating its last deflection; the node polls it at
    ``rate_hz``. ``opened``: an already open ``pyspacemouse`` device (tests pass one built over
    a scripted HID device); ``connect`` then only checks it.
    """

    def __init__(self, device: str = "", opened=None):
        self.device_name = device
        self._dev = opened

    def connect(self) -> None:
        if self._dev is not None:
            return
        try:
            import pyspacemouse
        except ImportError as err:
            raise TeleopError(
                "source 'spacemouse' needs pyspacemouse and hidapi "
                "(pip install 'equidiff_ros[spacemouse]'); or use source:=joy with the "
                "spacenav driver"
            ) from err
        try:
            connected = pyspacemouse.get_connected_devices()
        except Exception as err:  # hidapi missing its shared library, udev permissions, ...
            raise TeleopError(f"cannot enumerate HID devices for a SpaceMouse: {err}") from err
        supported = [name for name, *_ in pyspacemouse.get_supported_devices()]
        if not connected:
            raise TeleopError(
                "no SpaceMouse found: looked for USB HID devices of the supported 3Dconnexion "
                f"models ({', '.join(supported[:6])}, ...); check the cable/receiver and "
                "udev permissions (/dev/hidraw*), or use source:=joy with the spacenav driver"
            )
        name = self.device_name or connected[0]
        if name not in connected:
            raise TeleopError(f"SpaceMouse {name!r} not found; connected: {connected}")
        kwargs = {}
        convention = getattr(getattr(pyspacemouse, "AxisConvention", None), "ROS", None)
        if convention is not None:
            kwargs["axis_convention"] = convention
        try:
            self._dev = pyspacemouse.open(device=name, **kwargs)
        except Exception as err:
            raise TeleopError(f"cannot open SpaceMouse {name!r}: {err}") from err

    def read(self, now_ns: int) -> TeleopInput:
        """The device's latest state; ``stamp_ns`` = ``now_ns`` minus the age of its newest report."""
        if self._dev is None:
            raise TeleopError("SpaceMouse is not connected")
        # Drain every queued HID report (each carries only the translation or the rotation
        # half), so a slow tick never leaves the state lagging behind the device.
        s = self._dev.read()
        for _ in range(16):
            t_before = s.t
            s = self._dev.read()
            if s.t == t_before:
                break
        stamp = 0  # pyspacemouse's t < 0: no report since the device was opened
        if s.t >= 0:
            age_s = max(0.0, _hid_clock() - s.t)
            stamp = now_ns - int(age_s * NS_PER_S)
        return TeleopInput((s.x, s.y, s.z, s.roll, s.pitch, s.yaw), tuple(int(b) for b in s.buttons), stamp)

    def disconnect(self) -> None:
        if self._dev is not None:
            try:
                self._dev.close()
            finally:
                self._dev = None

    def __enter__(self) -> Self:
        self.connect()
        return self

    def __exit__(self, *exc) -> None:
        self.disconnect()


def _hid_clock() -> float:
    """The clock pyspacemouse stamps each processed HID report with (``SpaceMouseState.t``, s)."""
    from pyspacemouse import device

    return device.high_acc_clock()


def is_fresh(inp: TeleopInput | None, now_ns: int, timeout_s: float) -> bool:
    """The device reported ``inp`` at most ``timeout_s`` ago (a never-stamped input is not fresh)."""
    return inp is not None and inp.stamp_ns > 0 and now_ns - inp.stamp_ns <= timeout_s * NS_PER_S
