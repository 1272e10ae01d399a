"""Typed configuration of the franka node: safety limits, chunk scheduling, franky gains, rates.

Loaded from ``config/control.yaml`` with ``config.from_dict`` (unknown keys are errors with
their dotted path). The safety box the TCP is kept in comes from ``lab.yaml`` (``safety_box``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

from ..config import (
    REACH_M,
    UNIT_QUATERNION,
    ConfigError,
    SafetyBox,
    bounded,
    check_unit_quaternion,
    from_dict,
    load_mapping,
)
from ..robots.base import FR3_JOINT_SPEEDS_RAD_S, CartesianLimits, JointLimits
from ..robots.franky.config import FrankyConfig

# The Franka Hand opens to 80 mm.
HAND_MAX_WIDTH_M = 0.08
FR3_V = "the FR3's Cartesian velocity limit"
FR3_W = "the FR3's rotational velocity limit"


@dataclass(frozen=True)
class SafetyConfig:
    # diffusion_policy's real-robot limits
    max_linear_speed_m_s: float = bounded(
        0.25, unit="m/s", gt=0, le=CartesianLimits.translation_velocity_m_s, doc=FR3_V
    )
    max_angular_speed_rad_s: float = bounded(
        0.6, unit="rad/s", gt=0, le=CartesianLimits.rotation_velocity_rad_s, doc=FR3_W
    )
    # a chunk whose first live step is farther is rejected
    max_first_step_jump_m: float = bounded(0.08, unit="m", gt=0, le=0.2)
    max_first_step_rotation_rad: float = bounded(0.6, unit="rad", gt=0, le=math.pi)
    # Orientation cone: the tool axis may tilt at most this far from pointing straight down (yaw
    # is free). A chunk with any step outside is rejected; every command is also kept inside.
    max_tilt_rad: float = bounded(0.785, unit="rad", gt=0, lt=math.pi)
    # hold the measured pose this long after the last chunk's final step
    watchdog_timeout_s: float = bounded(0.5, unit="s", gt=0, le=5)
    # Commands keep this far inside the safety box (lab.yaml), so the arm's overshoot past a
    # command stopped at a wall stays inside it: the largest overshoot `equidiff bench safety
    # --faults out_of_box` measured at the speed limit on franky-sim with the braking below,
    # rounded up (docs/results/control.md, "The box margin, measured"). Measure it again on a real FR3.
    box_margin_m: float = bounded(0.005, unit="m", ge=0, le=0.05)
    # Commands heading for a wall brake at this deceleration so they arrive there at rest:
    # v <= sqrt(2 a d) at distance d. At 0.5 m/s^2 the arm follows the braking command, at 2 m/s^2
    # it did not and overshot further (docs/results/control.md, "The box margin, measured"); the braking
    # zone is v^2 / 2a (62 mm at the 0.25 m/s limit, 2.5 mm at 0.05 m/s).
    wall_deceleration_m_s2: float = bounded(
        0.5, unit="m/s^2", gt=0, le=CartesianLimits.translation_acceleration_m_s2, doc="the FR3's acceleration limit"
    )
    # The arm diverging from its command (the FR3's own reflexes stop this; franky-sim has none):
    # stop the motion, restart it where the arm is and hold.
    max_tracking_error_m: float = bounded(0.1, unit="m", gt=0, le=0.5)  # measured TCP this far from the last command
    # a joint this fast, per joint (robots.base.JointLimits: 95 % of the FR3's limits)
    max_joint_speeds_rad_s: tuple[float, ...] = bounded(
        JointLimits.max_joint_speeds_rad_s,
        unit="rad/s",
        gt=0,
        le=max(FR3_JOINT_SPEEDS_RAD_S),
        doc="and each joint's own",
    )
    # The FR3's joint position limits (robots.base.JointLimits): franky's tracker pushes
    # back near them, and a joint closer than joint_limit_margin_rad that still moves towards its
    # limit stops the motion like a divergence (hold until acknowledged).
    joint_position_min_rad: tuple[float, ...] = bounded(
        JointLimits.joint_position_min_rad, unit="rad", ge=-math.pi, le=math.pi, doc="and within the FR3's"
    )
    joint_position_max_rad: tuple[float, ...] = bounded(
        JointLimits.joint_position_max_rad, unit="rad", ge=-math.pi, le=4.6, doc="and within the FR3's"
    )
    joint_limit_margin_rad: float = bounded(0.05, unit="rad", ge=0, le=0.5)
    orthonormal_tol: float = bounded(1e-3, unit="", gt=0, le=0.1)
    # The hand's range: every width is clipped into it (the shipped policy predicted -0.059..0.154 m).
    min_gripper_width_m: float = bounded(0.0, unit="m", ge=0, le=HAND_MAX_WIDTH_M)
    max_gripper_width_m: float = bounded(0.08, unit="m", gt=0, le=HAND_MAX_WIDTH_M, doc="the Franka Hand's stroke")

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
        fast = [i + 1 for i, (v, top) in enumerate(zip(self.max_joint_speeds_rad_s, FR3_JOINT_SPEEDS_RAD_S)) if v > top]
        if fast:
            raise ValueError(
                f"max_joint_speeds_rad_s exceed the FR3's joint speed limits {FR3_JOINT_SPEEDS_RAD_S} rad/s "
                f"at joint(s) {fast}: {self.max_joint_speeds_rad_s}"
            )
        lo, hi = self.joint_position_min_rad, self.joint_position_max_rad
        if len(lo) != 7 or len(hi) != 7 or any(a >= b for a, b in zip(lo, hi)):
            raise ValueError(
                f"joint_position_min_rad / joint_position_max_rad must be 7 limits each, min < max, got {lo} / {hi}"
            )
        fr3_lo, fr3_hi = JointLimits.joint_position_min_rad, JointLimits.joint_position_max_rad
        if any(a < b - 1e-9 for a, b in zip(lo, fr3_lo)) or any(a > b + 1e-9 for a, b in zip(hi, fr3_hi)):
            raise ValueError(f"joint position limits {lo} / {hi} rad go beyond the FR3's {fr3_lo} / {fr3_hi}")
        if self.joint_limit_margin_rad < 0:
            raise ValueError(f"joint_limit_margin_rad must be >= 0, got {self.joint_limit_margin_rad}")
        if not 0 <= self.min_gripper_width_m <= self.max_gripper_width_m:
            raise ValueError("need 0 <= min_gripper_width_m <= max_gripper_width_m")


@dataclass(frozen=True)
class SchedulerConfig:
    # "linear" (default: 0.75 mm RMS on franky-sim, docs/control.md) or "cubic" (monotone C1 Hermite)
    interpolation: str = "linear"
    # steps earlier than now + this are dropped (diffusion_policy: 10 ms)
    drop_margin_s: float = bounded(0.01, unit="s", ge=0, le=1)
    # A chunk entirely in the past (e.g. a teleop target stamped "now") is still executed, as
    # "go there in lead_s", if its last step is at most this old; older chunks are rejected.
    max_step_age_s: float = bounded(0.25, unit="s", ge=0, le=2)
    lead_s: float = bounded(0.05, unit="s", gt=0, le=1)
    # A chunk whose header stamp lies further ahead of franka_node's clock than this is refused
    # (a stamp is an observation's time or "now", never the future): five control periods at
    # 200 Hz, room for clock skew between machines and for a /clock message in flight on
    # simulated time. A future stamp must not stretch the watchdog.
    max_future_stamp_s: float = bounded(0.025, unit="s", ge=0, le=0.5)
    # ... and so is one whose first step still to execute lies further ahead than this (it would
    # creep towards it and keep the watchdog quiet meanwhile): teleop's lead is 0.05 s, a policy
    # chunk's next step at most its dt (0.2 s).
    max_first_step_lead_s: float = bounded(1.0, unit="s", gt=0, le=5)

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
    control_hz: float = bounded(200.0, unit="Hz", ge=10, le=1000)  # rate of the safety filter + set_target loop
    # only command the gripper when its target moves this much
    gripper_deadband_m: float = bounded(0.005, unit="m", ge=0, le=HAND_MAX_WIDTH_M)
    home_on_start: bool = True
    # Home pose (TCP, base frame): inside lab.yaml's safety box (check_home_inside), gripper pointing down.
    home_position: tuple[float, float, float] = bounded((0.45, 0.0, 0.30), unit="m", ge=-REACH_M, le=REACH_M)
    home_quaternion_xyzw: tuple[float, float, float, float] = bounded(
        (1.0, 0.0, 0.0, 0.0), unit="", doc=UNIT_QUATERNION
    )
    # /franka/home (`equidiff lab home`): glide there this slowly, through the usual safety filter
    home_speed_m_s: float = bounded(0.05, unit="m/s", gt=0, le=CartesianLimits.translation_velocity_m_s, doc=FR3_V)
    home_angular_speed_rad_s: float = bounded(
        0.3, unit="rad/s", gt=0, le=CartesianLimits.rotation_velocity_rad_s, doc=FR3_W
    )
    safety: SafetyConfig = field(default_factory=SafetyConfig)
    scheduler: SchedulerConfig = field(default_factory=SchedulerConfig)
    franky: FrankyConfig = field(default_factory=FrankyConfig)

    def __post_init__(self):
        if self.home_speed_m_s <= 0 or self.home_angular_speed_rad_s <= 0:
            raise ValueError("home_speed_m_s and home_angular_speed_rad_s must be positive")
        if not 10 <= self.control_hz <= 1000:
            raise ValueError(f"control_hz must be within 10..1000, got {self.control_hz}")
        check_unit_quaternion(self.home_quaternion_xyzw, "home_quaternion_xyzw")


def load_control_config(path: str | Path) -> ControlConfig:
    return from_dict(ControlConfig, load_mapping(path), where=Path(path).name)


def check_home_inside(control: ControlConfig, box: SafetyBox) -> None:
    """control.yaml's home pose must lie where the safety filter (lab.yaml's box, less the floor and box
    margins) lets the TCP go: a home outside would be clipped, and the arm would never get there."""
    margin = control.safety.box_margin_m
    low, high = box.min_corner + margin, box.max_corner - margin
    home = control.home_position
    if not all(lo <= h <= hi for lo, h, hi in zip(low, home, high)):
        raise ConfigError(
            f"home_position {list(home)} m is outside the safety box the TCP may reach "
            f"({[round(v, 4) for v in low]} .. {[round(v, 4) for v in high]} m: lab.yaml's safety_box "
            f"less floor_margin_m and safety.box_margin_m)"
        )
