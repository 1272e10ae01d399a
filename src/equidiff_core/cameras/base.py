"""The camera interface every backend (realsense, twin, replay) implements.

Shape borrowed from LeRobot's ``cameras/``: an abstract context manager with
``connect`` / ``read`` / ``disconnect``, one small folder per backend with its own config
dataclass. A backend yields coloured point clouds in its *optical* frame, stamped with the
capture time, with the colour image they were made from; the camera node publishes them, the voxel node transforms them to the base
frame with the configured extrinsics.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass
from typing import Self

import numpy as np


class CameraError(RuntimeError):
    """The camera cannot deliver frames (not found, disconnected, timed out)."""


class NoFrameYet(CameraError):
    """No frame is due yet: the source's clock is paused (the twin on simulated time). Not a fault."""


@dataclass(frozen=True)
class CloudFrame:
    points: np.ndarray  # (N, 3) float32, metres, optical frame (x right, y down, z forward)
    colors: np.ndarray  # (N, 3) uint8 RGB
    stamp_ns: int  # capture time on the ROS clock (wall time on hardware, sim time in the twin)
    # the colour image the cloud's colours came from, RGB uint8 (H, W, 3), same instant; None where the
    # backend has none (replay of a bag)
    image: np.ndarray | None = None


@dataclass(frozen=True)
class CameraHealth:
    """How a camera has recovered from faults; camera_node puts it in /diagnostics."""

    resets: int = 0  # hardware resets issued after a stall
    reconnects: int = 0  # times the stream came back after a reset
    recovering: bool = False  # now between a stall and the stream's return
    last_recovery_reason: str = ""  # why the latest recovery began ("" = never)


class Camera(abc.ABC):
    """A source of coloured point clouds. Use as ``with make_camera(...) as cam: cam.read()``."""

    @abc.abstractmethod
    def connect(self) -> None:
        """Open the device or source; raise CameraError naming what was looked for if it is absent."""

    @abc.abstractmethod
    def read(self, timeout_s: float = 1.0) -> CloudFrame:
        """Block until the next frame (at most ``timeout_s``); raise CameraError on timeout."""

    @abc.abstractmethod
    def disconnect(self) -> None:
        """Release the device; safe to call twice."""

    @property
    @abc.abstractmethod
    def is_connected(self) -> bool: ...

    def health(self) -> CameraHealth:
        """Recovery counters; backends that do not recover by themselves report none."""
        return CameraHealth()

    def __enter__(self) -> Self:
        self.connect()
        return self

    def __exit__(self, *exc) -> None:
        self.disconnect()


def limit_depth(frame: CloudFrame, min_depth: float, max_depth: float) -> CloudFrame:
    """Drop points whose optical-frame depth (z) is outside [min_depth, max_depth] or not finite."""
    z = frame.points[:, 2]
    keep = (z >= min_depth) & (z <= max_depth)  # NaN compares False: dropped too
    if keep.all():
        return frame
    return CloudFrame(frame.points[keep], frame.colors[keep], frame.stamp_ns, frame.image)
