"""Robot-state and diagnostics messages, built through a ``rosmsg.MsgFactory`` (rclpy or rosbags).

``/franka/ee_pose`` (PoseStamped), ``/franka/joint_states`` (JointState: 7 arm joints + two
finger joints each at width/2), ``/franka/executed_target`` (PoseStamped) and the
``/diagnostics`` entries of the franka and policy nodes. Readers use attribute access
(``pose_from_msg``), so they take either flavour.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from .. import geometry
from ..robots.base import ARM_JOINT_NAMES, FINGER_JOINT_NAMES, RobotState
from ..rosmsg import MsgFactory

TCP_FRAME = "fr3_hand_tcp"  # franka_ros2's name for the TCP frame (also the chunk's joint name)

# diagnostic_msgs/DiagnosticStatus levels
OK, WARN, ERROR, STALE = 0, 1, 2, 3


def pose_stamped(factory: MsgFactory, pose: np.ndarray, stamp_ns: int, frame_id: str) -> Any:
    p, q = geometry.pos_quat_from_pose(pose)
    mk = factory.make
    return mk(
        "geometry_msgs/msg/PoseStamped",
        header=factory.header(stamp_ns, frame_id),
        pose=mk(
            "geometry_msgs/msg/Pose",
            position=mk("geometry_msgs/msg/Point", x=float(p[0]), y=float(p[1]), z=float(p[2])),
            orientation=mk("geometry_msgs/msg/Quaternion", x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])),
        ),
    )


def pose_from_msg(msg: Any) -> np.ndarray:
    """PoseStamped or Pose (either flavour) -> (4, 4); raises GeometryError on NaN / non-unit quaternions."""
    pose = getattr(msg, "pose", msg)
    p, o = pose.position, pose.orientation
    return geometry.pose_from_pos_quat([p.x, p.y, p.z], [o.x, o.y, o.z, o.w])


def tf_message(factory: MsgFactory, transforms: list[tuple[str, str, np.ndarray]], stamp_ns: int) -> Any:
    """``tf2_msgs/TFMessage`` of (parent frame, child frame, 4x4 pose of the child in the parent)."""
    mk = factory.make
    out = []
    for parent, child, pose in transforms:
        p, q = geometry.pos_quat_from_pose(pose)
        out.append(
            mk(
                "geometry_msgs/msg/TransformStamped",
                header=factory.header(stamp_ns, parent),
                child_frame_id=child,
                transform=mk(
                    "geometry_msgs/msg/Transform",
                    translation=mk("geometry_msgs/msg/Vector3", x=float(p[0]), y=float(p[1]), z=float(p[2])),
                    rotation=mk(
                        "geometry_msgs/msg/Quaternion", x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])
                    ),
                ),
            )
        )
    return mk("tf2_msgs/msg/TFMessage", transforms=out)


def joint_state(factory: MsgFactory, state: RobotState, stamp_ns: int) -> Any:
    width = float(state.gripper_width) if np.isfinite(state.gripper_width) else 0.0
    positions = [*map(float, state.joint_positions), width / 2, width / 2]
    velocities = [*map(float, state.joint_velocities), 0.0, 0.0]
    return factory.make(
        "sensor_msgs/msg/JointState",
        header=factory.header(stamp_ns, ""),
        name=[*ARM_JOINT_NAMES, *FINGER_JOINT_NAMES],
        position=factory.float64_array(positions),
        velocity=factory.float64_array(velocities),
        effort=factory.float64_array([]),
    )


def gripper_width_from_joint_state(msg: Any) -> float | None:
    """Gripper width = sum of the two finger joints; None if the message carries no gripper state
    (no finger joints, e.g. an arm-only publisher, or fewer positions than names: malformed).
    The value may be NaN/inf if the publisher sent that: callers check ``isfinite``."""
    names = list(msg.name)
    try:
        return float(sum(msg.position[names.index(n)] for n in FINGER_JOINT_NAMES))
    except (ValueError, IndexError):
        return None


def diagnostic_array(
    factory: MsgFactory, stamp_ns: int, name: str, hardware_id: str, level: int, message: str, values: Mapping[str, Any]
) -> Any:
    mk = factory.make
    # DiagnosticStatus.level is a ROS `byte`: rclpy wants bytes (an int serialises as garbage),
    # rosbags an int.
    from ..rosmsg import RclpyFactory

    level = bytes([int(level)]) if isinstance(factory, RclpyFactory) else int(level)
    status = mk(
        "diagnostic_msgs/msg/DiagnosticStatus",
        level=level,
        name=name,
        message=message,
        hardware_id=hardware_id,
        values=[mk("diagnostic_msgs/msg/KeyValue", key=str(k), value=_fmt(v)) for k, v in values.items()],
    )
    return mk("diagnostic_msgs/msg/DiagnosticArray", header=factory.header(stamp_ns, ""), status=[status])


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.3f}"
    return str(v)
