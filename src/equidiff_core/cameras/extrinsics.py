"""The cameras' configured extrinsics as ROS transforms."""

from __future__ import annotations

from ..wire.rosmsg import tf_message


def extrinsics_tf_message(cameras, base_frame: str, stamp_ns: int, factory):
    """``tf2_msgs/TFMessage`` with base_frame -> each camera's optical frame (the configured T_base_optical)."""
    return tf_message(factory, [(base_frame, cam.frame_id, cam.extrinsics.matrix()) for cam in cameras], stamp_ns)
