"""Typed configuration of the franka node: safety limits, chunk scheduling, franky gains, rates.

Loaded from ``config/control.yaml`` with ``config.from_dict`` (unknown keys are errors with
their dotted path). The safety box the TCP is kept in comes from ``lab.yaml`` (``safety_box``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from ..config import ConfigError, from_dict, load_yaml
from ..robots.base import JointLimits
from ..robots.franky.config import FrankyConfig


@dataclass(frozen=True)
class SafetyConfig:
    max_linear_speed_m_s: float = 0.25  # diffusion_policy's real-robot limits
    max_angular_speed_rad_s: float = 0.6
    max_first_step_jump_m: float = 0.08  # a chunk whose first live step is farther is rejected
    max_first_step_rotation_rad: float = 0.6
    # Orientation cone: the tool axis may tilt at most this far from pointing straight down (yaw
    # is free). A chunk with any step outside is rejected; every command is also kept inside.
    max_tilt_rad: float = 0.785
    watchdog_timeout_s: float = 0.5  # hold the measured pose this long after the last chunk's final step
    # Commands keep this far inside the safety box (lab.yaml), so the arm's overshoot past a
    # command stopped at a wall stays inside it: the largest overshoot `equidiff bench safety
    # --faults out_of_box` measured at the speed limit on franky-sim with the braking below,
    # 4.11 mm (eight runs, 2.60-4.11 mm, 2026-11-27; docs/control.md), rounded up. Measure it
    # again on a real FR3.
    box_margin_m: float = 0.005
    # Commands heading for a wall brake at this deceleration so they arrive there at rest:
    # v <= sqrt(2 a d) at distance d. 0.5 m/s^2 took the overshoot from 2-10 mm (2 m/s^2, the
    # arm's ~30 ms response could not follow) to 0.6-2.8 mm; the braking zone is v^2 / 2a
    # (62 mm at the 0.25 m/s limit, 2.5 mm at 0.05 m/s).
    wall_deceleration_m_s2: float = 0.5
    # The arm diverging from its command (the FR3's own reflexes stop this; franky-sim has none):
    # stop the motion, restart it where the arm is and hold.
    max_tracking_error_m: float = 0.1  # measured TCP this far from the last command
    # a joint this fast, per joint (robots.base.JointLimits: 95 % of the FR3's limits)
    max_joint_speeds_rad_s: tuple[float, ...] = JointLimits.max_joint_speeds_rad_s
    # The FR3's joint position limits (robots.base.JointLimits): franky's tracker pushes
    # back near them, and a joint closer than joint_limit_margin_rad that still moves towards its
    # limit stops the motion like a divergence (hold until acknowledged).
    joint_position_min_rad: tuple[float, ...] = JointLimits.joint_position_min_rad
    joint_position_max_rad: tuple[float, ...] = JointLimits.joint_position_max_rad
    joint_limit_margin_rad: float = 0.05
    orthonormal_tol: float = 1e-3
    # The hand's range: every width is clipped into it (the shipped policy predicted -0.059..0.154 m).
    min_gripper_width_m: float = 0.0
    max_gripper_width_m: float = 0.08

    def __post_init__(self):
        for name in (
            "max_linear_speed_m_s",
            "max_angular_speed_rad_s",
            "max_first_step_jump_m",
            "max_first_step_rotation_rad",
            "watchdog_timeout_s",
            "orthonormal_tol",
            "max_tracking_error_m",
            "max_tilt_rad",
        ):
            if getattr(self, name) <= 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        if len(self.max_joint_speeds_rad_s) != 7 or min(self.max_joint_speeds_rad_s) <= 0:
            raise ValueError(f"max_joint_speeds_rad_s must be 7 positive speeds, got {self.max_joint_speeds_rad_s}")
        if self.box_margin_m < 0:
            raise ValueError(f"box_margin_m must be >= 0, got {self.box_margin_m}")
        if self.wall_deceleration_m_s2 <= 0:
            raise ValueError(f"wall_deceleration_m_s2 must be positive, got {self.wall_deceleration_m_s2}")
        if self.max_tilt_rad >= 3.14159:
            raise ValueError(f"max_tilt_rad must be below pi, got {self.max_tilt_rad}")
        lo, hi = self.joint_position_min_rad, self.joint_position_max_rad
        if len(lo) != 7 or len(hi) != 7 or any(a >= b for a, b in zip(lo, hi)):
            raise ValueError(
                f"joint_position_min_rad / joint_position_max_rad must be 7 limits each, min < max, got {lo} / {hi}"
            )
        if self.joint_limit_margin_rad < 0:
            raise ValueError(f"joint_limit_margin_rad must be >= 0, got {self.joint_limit_margin_rad}")
        if not 0 <= self.min_gripper_width_m <= self.max_gripper_width_m:
            raise ValueError("need 0 <= min_gripper_width_m <= max_gripper_width_m")


@dataclass(frozen=True)
class SchedulerConfig:
    # "linear" (default: 0.75 mm RMS on franky-sim, docs/control.md) or "cubic" (monotone C1 Hermite)
    interpolation: str = "linear"
    drop_margin_s: float = 0.01  # steps earlier than now + this are dropped (diffusion_policy: 10 ms)
    # A chunk entirely in the past (e.g. a teleop target stamped "now") is still executed, as
    # "go there in lead_s", if its last step is at most this old; older chunks are rejected.
    max_step_age_s: float = 0.25
    lead_s: float = 0.05
    # A chunk whose header stamp lies further ahead of franka_node's clock than this is refused
    # (a stamp is an observation's time or "now", never the future): five control periods at
    # 200 Hz, room for clock skew between machines (chrony on a LAN: well under 1 ms) and for a
    # /clock message in flight on simulated time. A future stamp must not stretch the watchdog.
    max_future_stamp_s: float = 0.025
    # ... and so is one whose first step still to execute lies further ahead than this (it would
    # creep towards it and keep the watchdog quiet meanwhile): teleop's lead is 0.05 s, a policy
    # chunk's next step at most its dt (0.2 s).
    max_first_step_lead_s: float = 1.0

    def __post_init__(self):
        if self.interpolation not in ("cubic", "linear"):
            raise ValueError(f"interpolation must be 'cubic' or 'linear', got {self.interpolation!r}")
        if self.lead_s <= 0:
            raise ValueError("lead_s must be positive")
        if not self.max_future_stamp_s >= 0:
            raise ValueError(f"max_future_stamp_s must be >= 0, got {self.max_future_stamp_s}")
        if not self.max_first_step_lead_s > 0:
            raise ValueError(f"max_first_step_lead_s must be positive, got {self.max_first_step_lead_s}")


@dataclass(frozen=True)
class ControlConfig:
    control_hz: float = 200.0  # rate of the safety filter + set_target loop
    gripper_deadband_m: float = 0.005  # only command the gripper when its target moves this much
    home_on_start: bool = True
    # Home pose (TCP, base frame): inside the workspace, gripper pointing down.
    home_position: tuple[float, float, float] = (0.45, 0.0, 0.30)
    home_quaternion_xyzw: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)
    # /franka/home (`equidiff lab home`): glide there this slowly, through the usual safety filter
    home_speed_m_s: float = 0.05
    home_angular_speed_rad_s: float = 0.3
    safety: SafetyConfig = field(default_factory=SafetyConfig)
    scheduler: SchedulerConfig = field(default_factory=SchedulerConfig)
    franky: FrankyConfig = field(default_factory=FrankyConfig)

    def __post_init__(self):
        if self.home_speed_m_s <= 0 or self.home_angular_speed_rad_s <= 0:
            raise ValueError("home_speed_m_s and home_angular_speed_rad_s must be positive")
        if not 10 <= self.control_hz <= 1000:
            raise ValueError(f"control_hz must be within 10..1000, got {self.control_hz}")


def load_control_config(path: str | Path) -> ControlConfig:
    data = load_yaml(path)
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping at the top level")
    return from_dict(ControlConfig, data, where=Path(path).name)
