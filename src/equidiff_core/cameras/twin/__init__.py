"""Simulated RealSense D455 for the digital twin: MuJoCo offscreen RGB + depth -> coloured cloud (``make_camera("twin", ...)``).

* ``camera``: ``TwinCamera``, its pinhole ``Intrinsics``, depth -> points and the depth sensor's degradation
* ``config``: ``TwinCameraOptions`` (camera_node's ``backend_options``)
"""

from .camera import Intrinsics, StateSource, TwinCamera, degrade_depth, depth_to_points
from .config import TwinCameraOptions

__all__ = ["Intrinsics", "StateSource", "TwinCamera", "TwinCameraOptions", "degrade_depth", "depth_to_points"]
