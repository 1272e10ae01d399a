"""Camera backends behind one interface (``base.Camera``), chosen by name.

``make_camera("realsense" | "replay" | "twin", camera_config, **backend_kwargs)`` imports the
backend lazily, so a machine without pyrealsense2 or MuJoCo can still use the others.
"""

from __future__ import annotations

import importlib

from ..config import CameraConfig
from .base import Camera, CameraError, CameraHealth, CloudFrame, NoFrameYet

# backend name -> (module relative to this package, class name)
BACKENDS: dict[str, tuple[str, str]] = {
    "realsense": (".realsense", "RealSenseCamera"),
    "replay": (".replay", "ReplayCamera"),
    "twin": (".twin", "TwinCamera"),
}

__all__ = [
    "BACKENDS",
    "Camera",
    "CameraError",
    "CameraHealth",
    "CloudFrame",
    "NoFrameYet",
    "extrinsics_tf_message",
    "limit_depth",
    "make_camera",
]


def make_camera(backend: str, camera: CameraConfig, **backend_kwargs) -> Camera:
    """Build (not connect) the camera ``camera`` with ``backend``; kwargs go to the backend."""
    if backend not in BACKENDS:
        raise CameraError(f"unknown camera backend {backend!r}; choose one of {sorted(BACKENDS)}")
    module_name, class_name = BACKENDS[backend]
    try:
        module = importlib.import_module(module_name, __name__)
    except ImportError as err:
        raise CameraError(f"camera backend {backend!r} is unavailable: {err}") from err
    return getattr(module, class_name)(camera, **backend_kwargs)


def limit_depth(frame: CloudFrame, min_depth: float, max_depth: float) -> CloudFrame:
    """Drop points whose optical-frame depth (z) is outside [min_depth, max_depth] or not finite."""
    z = frame.points[:, 2]
    keep = (z >= min_depth) & (z <= max_depth)  # NaN compares False: dropped too
    if keep.all():
        return frame
    return CloudFrame(frame.points[keep], frame.colors[keep], frame.stamp_ns, frame.image)


def extrinsics_tf_message(cameras, base_frame: str, stamp_ns: int, factory):
    """``tf2_msgs/TFMessage`` with base_frame -> each camera's optical frame (the configured T_base_optical)."""
    from ..rosmsg import tf_message

    return tf_message(factory, [(base_frame, cam.frame_id, cam.extrinsics.matrix()) for cam in cameras], stamp_ns)
