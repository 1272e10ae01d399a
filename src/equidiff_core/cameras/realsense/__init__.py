"""Intel RealSense (D4xx) backend via pyrealsense2: ``make_camera("realsense", camera_config)``."""

from .camera import RealSenseCamera, depth_to_cloud, pixel_rays
from .config import RealSenseOptions

__all__ = ["RealSenseCamera", "RealSenseOptions", "depth_to_cloud", "pixel_rays"]
