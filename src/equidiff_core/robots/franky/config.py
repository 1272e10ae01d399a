"""Settings of the franky backend: impedance gains, friction and posture feed-forward, gripper, collision reflex.

``config/control.yaml``'s ``franky:`` section (``control.ControlConfig.franky``).
"""

from __future__ import annotations

from dataclasses import dataclass

from ...config import bounded


@dataclass(frozen=True)
class FrankyConfig:
    """franky 2.0 backend: a CartesianImpedanceTracker streamed at ``ControlConfig.control_hz``."""

    # on franky-sim a 5 Hz chunk stream tracked 3.5 mm RMS at 3000 N/m, 8-9 mm at 1000
    translational_stiffness: float = bounded(3000.0, unit="N/m", gt=0, le=10000)
    rotational_stiffness: float = bounded(150.0, unit="Nm/rad", gt=0, le=1000)
    # Joint friction feed-forward (Nm, Nms/rad). Defaults are franky-sim's own MuJoCo values
    # (fr3.xml frictionloss / damping); on a real FR3 identify them or set them to zero.
    friction_coulomb: tuple[float, ...] = bounded(
        (1.137, 1.137, 1.137, 1.137, 0.763, 0.44, 0.248), unit="Nm", ge=0, le=10
    )
    friction_viscous: tuple[float, ...] = bounded((0.21,) * 7, unit="Nms/rad", ge=0, le=10)
    friction_max_torque: float = bounded(2.0, unit="Nm", ge=0, le=20)
    # Null-space posture task towards the joint configuration where streaming first started (the
    # home pose): without it the redundant elbow drifts under Cartesian impedance until joints
    # hit their limits and the arm leaves the workspace (2.8 rad in 30 s of yawing targets on
    # franky-sim). 0 disables it.
    posture_stiffness: float = bounded(10.0, unit="Nm/rad", ge=0, le=100)
    posture_max_torque: float = bounded(5.0, unit="Nm", ge=0, le=20)  # per joint
    relative_dynamics_factor: float = bounded(0.15, unit="", gt=0, le=1)  # for the blocking move to the home pose only
    gripper_speed_m_s: float = bounded(0.05, unit="m/s", gt=0, le=0.2)
    gripper_force_n: float = bounded(20.0, unit="N", gt=0, le=140, doc="the Franka Hand's peak force")
    # wide, so a grasp commanded below the object holds
    gripper_epsilon_outer_m: float = bounded(0.03, unit="m", ge=0, le=0.08)
    # warn when one gripper command runs longer (0.08 m takes 1.6 s)
    gripper_command_timeout_s: float = bounded(5.0, unit="s", gt=0, le=60)
    # The FR3's collision reflex (Robot.set_collision_behavior, set once on connect): a joint torque
    # (Nm) or TCP force (N, x y z; Nm about x y z) beyond these stops the arm. libfranka's example
    # defaults (examples_common.cpp setDefaultBehavior); franky-sim acknowledges and ignores them.
    collision_torque_thresholds_nm: tuple[float, ...] = bounded(
        (20.0, 20.0, 18.0, 18.0, 16.0, 14.0, 12.0), unit="Nm", gt=0, le=100
    )
    collision_force_thresholds_n: tuple[float, ...] = bounded(
        (20.0, 20.0, 20.0, 25.0, 25.0, 25.0), unit="N or Nm", gt=0, le=100
    )
    # franky's tracker pushes joints back from their limits (SafetyConfig.joint_position_*) within this
    joint_limit_activation_rad: float = bounded(0.1, unit="rad", gt=0, le=0.5)

    def __post_init__(self):
        if len(self.friction_coulomb) != 7 or len(self.friction_viscous) != 7:
            raise ValueError("friction_coulomb and friction_viscous need 7 values (one per joint)")
        if len(self.collision_torque_thresholds_nm) != 7 or min(self.collision_torque_thresholds_nm) <= 0:
            raise ValueError(
                f"collision_torque_thresholds_nm must be 7 positive torques, got {self.collision_torque_thresholds_nm}"
            )
        if len(self.collision_force_thresholds_n) != 6 or min(self.collision_force_thresholds_n) <= 0:
            raise ValueError(
                f"collision_force_thresholds_n must be 6 positive values, got {self.collision_force_thresholds_n}"
            )
        if self.joint_limit_activation_rad <= 0:
            raise ValueError(f"joint_limit_activation_rad must be positive, got {self.joint_limit_activation_rad}")
