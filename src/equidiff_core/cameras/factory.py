"""Building a camera backend by name (camera_node's ``backend`` parameter).

Backends are imported when first asked for, so a machine without pyrealsense2 or MuJoCo can still use the others.
"""

from __future__ import annotations

import importlib

from ..config import CameraConfig
from .base import Camera, CameraError

# backend name -> (module relative to this package, class name)
BACKENDS: dict[str, tuple[str, str]] = {
    "realsense": (".realsense", "RealSenseCamera"),
    "replay": (".replay", "ReplayCamera"),
    "twin": (".twin", "TwinCamera"),
}


def make_camera(backend: str, camera: CameraConfig, **backend_kwargs) -> Camera:
    """Build (not connect) the camera ``camera`` with ``backend``; kwargs go to the backend."""
    if backend not in BACKENDS:
        raise CameraError(f"unknown camera backend {backend!r}; choose one of {sorted(BACKENDS)}")
    module_name, class_name = BACKENDS[backend]
    try:
        module = importlib.import_module(module_name, __package__)
    except ImportError as err:
        raise CameraError(f"camera backend {backend!r} is unavailable: {err}") from err
    return getattr(module, class_name)(camera, **backend_kwargs)
