"""Settings of the franky backend: impedance gains, friction and posture feed-forward, gripper, collision reflex.

``config/control.yaml``'s ``franky:`` section (``control.ControlConfig.franky``).
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class FrankyConfig:
    """franky 2.0 backend: a CartesianImpedanceTracker streamed at ``ControlConfig.control_hz``."""

    translational_stiffness: float = (
        3000.0  # N/m; on franky-sim a 5 Hz chunk stream tracked 3.5 mm RMS at 3000, 8-9 mm at 1000
    )
    rotational_stiffness: float = 150.0  # Nm/rad
    # Joint friction feed-forward (Nm, Nms/rad). Defaults are franky-sim's own MuJoCo values
    # (fr3.xml frictionloss / damping); on a real FR3 identify them or set them to zero.
    friction_coulomb: tuple[float, ...] = (1.137, 1.137, 1.137, 1.137, 0.763, 0.44, 0.248)
    friction_viscous: tuple[float, ...] = (0.21, 0.21, 0.21, 0.21, 0.21, 0.21, 0.21)
    friction_max_torque: float = 2.0
    # Null-space posture task towards the joint configuration where streaming first started (the
    # home pose): without it the redundant elbow drifts under Cartesian impedance until joints
    # hit their limits and the arm leaves the workspace (2.8 rad in 30 s of yawing targets on
    # franky-sim). 0 disables it.
    posture_stiffness: float = 10.0  # Nm/rad
    posture_max_torque: float = 5.0  # Nm per joint
    relative_dynamics_factor: float = 0.15  # for the blocking move to the home pose only
    gripper_speed_m_s: float = 0.05
    gripper_force_n: float = 20.0
    gripper_epsilon_outer_m: float = 0.03  # wide, so a grasp commanded below the object holds
    gripper_command_timeout_s: float = 5.0  # warn when one gripper command runs longer (0.08 m takes 1.6 s)
    # The FR3's collision reflex (Robot.set_collision_behavior, set once on connect): a joint torque
    # (Nm) or TCP force (N, x y z; Nm about x y z) beyond these stops the arm. libfranka's example
    # defaults (examples_common.cpp setDefaultBehavior); franky-sim acknowledges and ignores them.
    collision_torque_thresholds_nm: tuple[float, ...] = (20.0, 20.0, 18.0, 18.0, 16.0, 14.0, 12.0)
    collision_force_thresholds_n: tuple[float, ...] = (20.0, 20.0, 20.0, 25.0, 25.0, 25.0)
    # franky's tracker pushes joints back from their limits (SafetyConfig.joint_position_*) within this
    joint_limit_activation_rad: float = 0.1

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
