"""Options of the replay camera backend: camera_node's ``bag`` / ``loop`` / ``rate`` / ``restamp`` parameters."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class ReplayOptions:
    """Where a replayed camera's clouds come from and how they are paced (``make_camera("replay", cam, **options)``)."""

    bag: str | Path | None = None  # a rosbag2 directory (required)
    topic: str | None = None  # default: the camera's own topic, /cameras/<name>/points
    loop: bool = True  # start again at the end; off: ReplayFinished after the last frame
    rate: float = 1.0  # playback speed (2.0: twice the recorded pace)
    restamp: bool = True  # stamp frames with the reading clock (live-looking data), else keep the recorded stamps
