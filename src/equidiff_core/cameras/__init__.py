"""Camera backends behind one interface (``base.Camera``), chosen by name.

``make_camera("realsense" | "replay" | "twin", camera_config, **backend_kwargs)`` (``factory``) imports the
backend lazily, so a machine without pyrealsense2 or MuJoCo can still use the others. One package per
backend, each with its options dataclass.
"""

from .base import Camera, CameraError, CameraHealth, CloudFrame, NoFrameYet, limit_depth
from .extrinsics import extrinsics_tf_message
from .factory import BACKENDS, make_camera

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
