"""Replay camera backend: a camera's clouds from a recorded rosbag2 directory (``make_camera("replay", ...)``).

* ``camera``: ``ReplayCamera`` (paced on the wall clock, restamped by default)
* ``config``: ``ReplayOptions``
"""

from .camera import POINTCLOUD2, ReplayCamera, ReplayFinished
from .config import ReplayOptions

__all__ = ["POINTCLOUD2", "ReplayCamera", "ReplayFinished", "ReplayOptions"]
