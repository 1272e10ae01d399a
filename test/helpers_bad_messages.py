"""Bad messages of every kind a node boundary must refuse, for the live-node test and the fuzz tests.

Each builder returns ``{kind: message}`` made with a ``MsgFactory`` (rclpy or rosbags flavour),
every message derived from a good one by one defect, so a decoder that accepts one has missed
exactly that defect.
"""

from __future__ import annotations

import numpy as np

from equidiff_core import geometry
from equidiff_core.config import Workspace
from equidiff_core.robots.base import RobotState
from equidiff_core.wire.chunk import PoseChunk, chunk_to_msg
from equidiff_core.wire.pointcloud import INT16, UINT8, cloud_to_msg, grid_to_voxel_msg
from equidiff_core.wire.rosmsg import joint_state, pose_stamped

DAY_NS = 86_400 * 1_000_000_000


def _set_datatype(msg, name: str, datatype: int) -> None:
    for field in msg.fields:
        if field.name == name:
            field.datatype = datatype


def _truncate(msg, factory) -> None:
    data = bytes(memoryview(msg.data).cast("B"))
    msg.data = factory.uint8_array(data[: len(data) - 5])


def bad_clouds(factory, points, colors, stamp_ns: int, frame_id: str) -> dict:
    """Camera clouds (x y z rgb) with one defect each."""

    def good():
        return cloud_to_msg(points, colors, stamp_ns, frame_id, factory)

    out = {}
    out["rgb_declared_uint8"] = m = good()  # 400 points would decode with 100 colours
    _set_datatype(m, "rgb", UINT8)
    out["x_declared_int16"] = m = good()
    _set_datatype(m, "x", INT16)
    out["no_z"] = m = good()
    m.fields = [f for f in m.fields if f.name != "z"]
    out["truncated"] = m = good()
    _truncate(m, factory)
    out["point_step_12"] = m = good()
    m.point_step = 12
    out["wrong_frame"] = cloud_to_msg(points, colors, stamp_ns, "somewhere_else", factory)
    bad_points = np.array(points, dtype=np.float32, copy=True)
    bad_points[0] = np.nan
    out["nan_point"] = cloud_to_msg(bad_points, colors, stamp_ns, frame_id, factory)
    return out


def voxel_msg(factory, grid, ws: Workspace, stamp_ns: int, frame_id: str):
    return grid_to_voxel_msg(grid, ws.lower, ws.voxel_size, stamp_ns, frame_id, factory)


def bad_voxel_msgs(factory, grid, ws: Workspace, stamp_ns: int, frame_id: str) -> dict:
    """Occupied-voxel clouds with one defect each, against the grid ``ws`` in ``frame_id``."""

    def good():
        return voxel_msg(factory, grid, ws, stamp_ns, frame_id)

    out = {}
    half = Workspace(ws.center, ws.edge, ws.resolution // 2)  # a 32^3 grid over the same space
    small = np.zeros((4, half.resolution, half.resolution, half.resolution), np.uint8)
    small[:, 3:6, 4:7, 5:8] = 200
    out["grid_32"] = voxel_msg(factory, small, half, stamp_ns, frame_id)
    moved = Workspace(tuple(np.asarray(ws.center) + 0.05), ws.edge, ws.resolution)
    out["origin_moved"] = voxel_msg(factory, grid, moved, stamp_ns, frame_id)
    out["i_declared_int16"] = m = good()  # an index of -1 as INT16 would wrap to 63 as UINT16
    _set_datatype(m, "i", INT16)
    out["rgb_declared_uint8"] = m = good()
    _set_datatype(m, "rgb", UINT8)
    out["no_k"] = m = good()
    m.fields = [f for f in m.fields if f.name != "k"]
    out["truncated"] = m = good()
    _truncate(m, factory)
    out["wrong_frame"] = voxel_msg(factory, grid, ws, stamp_ns, "somewhere_else")
    out["duplicate_voxel"] = m = good()
    data = bytes(memoryview(m.data).cast("B"))
    m.data = factory.uint8_array(data + data[:24])
    m.width = m.width + 1
    m.row_step = m.row_step + 24
    return out


def hold_chunk(position, stamp_ns: int, steps: int = 4, dt_ns: int = 200_000_000) -> PoseChunk:
    """A chunk holding the tool pointing down at ``position``, steps from ``stamp_ns``."""
    pose = geometry.pose_from_pos_quat(position, (1.0, 0.0, 0.0, 0.0))
    times = stamp_ns + np.arange(steps, dtype=np.int64) * dt_ns
    return PoseChunk(int(stamp_ns), times, np.repeat(pose[None], steps, axis=0), np.full(steps, 0.08))


def bad_chunks(factory, position, stamp_ns: int, frame_id: str) -> dict:
    """Command chunks with one defect each (``position``: where the arm is, so only the defect fails)."""

    def good(stamp=stamp_ns, frame=frame_id):
        return chunk_to_msg(hold_chunk(position, stamp), factory, frame)

    out = {}
    out["stamped_a_day_ahead"] = good(stamp_ns + DAY_NS)
    out["wrong_frame"] = good(frame="somewhere_else")
    out["joint_names_swapped"] = m = good()
    m.joint_names = list(reversed(m.joint_names))
    out["nan_position"] = m = good()
    m.points[1].transforms[0].translation.x = float("nan")
    out["non_unit_quaternion"] = m = good()
    m.points[0].transforms[0].rotation.w = 2.0
    out["one_transform"] = m = good()
    m.points[2].transforms = m.points[2].transforms[:1]
    return out


def bad_ee_poses(factory, pose, stamp_ns: int, frame_id: str) -> dict:
    """TCP poses (PoseStamped) with one defect each that the decoder itself refuses (the stamp is good)."""

    def good(frame=frame_id):
        return pose_stamped(factory, pose, stamp_ns, frame)

    out = {}
    out["wrong_frame"] = good(frame="somewhere_else")
    out["nan_position"] = m = good()
    m.pose.position.y = float("nan")
    out["nan_quaternion"] = m = good()
    m.pose.orientation.z = float("nan")
    out["non_unit_quaternion"] = m = good()  # |q| = 1.5: a normaliser would have hidden a corrupted rotation
    o = m.pose.orientation
    o.x, o.y, o.z, o.w = 1.5 * o.x, 1.5 * o.y, 1.5 * o.z, 1.5 * o.w
    return out


def robot_state(position, width: float = 0.04) -> RobotState:
    """A state of the arm holding the tool pointing down at ``position``."""
    pose = geometry.pose_from_pos_quat(position, (1.0, 0.0, 0.0, 0.0))
    q = np.array([0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785])
    return RobotState(0, pose, q, np.zeros(7), width)


def bad_joint_states(factory, state: RobotState, stamp_ns: int) -> dict:
    """JointStates (7 arm joints + two fingers) with one defect each that the decoder refuses."""

    def good():
        return joint_state(factory, state, stamp_ns)

    def set_positions(m, positions):
        m.position = factory.float64_array(positions)

    out = {}
    out["one_position_short"] = m = good()
    set_positions(m, list(m.position)[:-1])
    out["name_twice"] = m = good()
    m.name = [*m.name[:-1], m.name[-2]]  # the second finger named as the first
    out["nan_finger"] = m = good()
    set_positions(m, [*list(m.position)[:-1], float("nan")])
    out["nan_arm_joint"] = m = good()
    set_positions(m, [float("nan"), *list(m.position)[1:]])
    out["width_beyond_stroke"] = m = good()  # 0.12 m: the hand opens to 0.08
    set_positions(m, [*list(m.position)[:-2], 0.06, 0.06])
    out["negative_width"] = m = good()
    set_positions(m, [*list(m.position)[:-2], -0.01, -0.01])
    out["velocities_short"] = m = good()
    m.velocity = factory.float64_array(list(m.velocity)[:3])
    return out
