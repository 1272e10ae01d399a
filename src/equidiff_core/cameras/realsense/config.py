"""Options of the RealSense backend: the ``options`` mapping of a camera in config/lab.yaml."""

from __future__ import annotations

from dataclasses import dataclass

from ...config import bounded

VISUAL_PRESETS = ("custom", "default", "hand", "high_accuracy", "high_density", "medium_density")


@dataclass(frozen=True)
class RealSenseOptions:
    """Stream, filter and sensor settings; the colour stream uses the camera's width/height/fps.

    Labs fix exposure and white balance so that colours (and hence the voxel grid's colour
    channels) do not drift between demonstrations and evaluation: give ``exposure_us`` and
    ``white_balance_k``; leave them out for auto.

    Recovery (a stalled or unplugged camera, see ``RealSenseCamera.read``): after
    ``reset_after_timeouts`` frame timeouts in a row the pipeline is stopped, the device is
    hardware-reset and, once its serial re-enumerates (at most ``reenumerate_timeout_s``), the
    pipeline is started again and every option here re-applied by the same code as the first
    connect. A camera that does not come back is tried again after ``reconnect_backoff_s``,
    doubling up to ``reconnect_backoff_max_s``, for as long as the node runs.
    """

    # default: the colour width/height (the D455 supports 848x480 for both)
    depth_width: int | None = bounded(None, unit="px", gt=0, le=4096)
    depth_height: int | None = bounded(None, unit="px", gt=0, le=4096)
    decimation: int = bounded(
        1, unit="", ge=1, le=8
    )  # 1 = off; 2..8 divides the depth resolution (and noise, and cost)
    spatial: bool = False  # edge-preserving spatial smoothing (in disparity space)
    temporal: bool = False  # temporal smoothing over the last frames (in disparity space)
    hole_filling: bool = False  # fill holes from the nearest valid neighbour
    exposure_us: float | None = bounded(None, unit="us", gt=0, le=1_000_000)  # colour exposure; None = auto
    white_balance_k: float | None = bounded(None, unit="K", gt=0, le=20_000)  # colour white balance; None = auto
    depth_exposure_us: float | None = bounded(None, unit="us", gt=0, le=1_000_000)  # None = auto
    laser_power: float | None = bounded(None, unit="mW", gt=0, le=1000)  # emitter power; None = device default
    visual_preset: str | None = None  # one of VISUAL_PRESETS; None = device default
    # consecutive frame timeouts (each the reader's timeout, 1 s in camera_node) before a reset
    reset_after_timeouts: int = bounded(3, unit="timeouts", ge=1, le=100)
    # wait this long for the serial to come back after a reset (a D4xx takes a few s)
    reenumerate_timeout_s: float = bounded(10.0, unit="s", gt=0, le=120)
    # pause before the next reset after a failed one; doubles each time...
    reconnect_backoff_s: float = bounded(1.0, unit="s", gt=0, le=600)
    reconnect_backoff_max_s: float = bounded(30.0, unit="s", gt=0, le=3600)  # ...up to this

    def __post_init__(self):
        if not 1 <= self.decimation <= 8:
            raise ValueError(f"decimation must be 1..8, got {self.decimation}")
        if (self.depth_width is None) != (self.depth_height is None):
            raise ValueError("give both depth_width and depth_height, or neither")
        if self.reset_after_timeouts < 1:
            raise ValueError(f"reset_after_timeouts must be >= 1, got {self.reset_after_timeouts}")
        if self.reconnect_backoff_max_s < self.reconnect_backoff_s:
            raise ValueError(
                f"reconnect_backoff_max_s ({self.reconnect_backoff_max_s}) must be >= "
                f"reconnect_backoff_s ({self.reconnect_backoff_s})"
            )
        for name in (
            "exposure_us",
            "white_balance_k",
            "depth_exposure_us",
            "laser_power",
            "reenumerate_timeout_s",
            "reconnect_backoff_s",
        ):
            value = getattr(self, name)
            if value is not None and value <= 0:
                raise ValueError(f"{name} must be positive, got {value}")
        if self.visual_preset is not None and self.visual_preset not in VISUAL_PRESETS:
            raise ValueError(f"visual_preset must be one of {VISUAL_PRESETS}, got {self.visual_preset!r}")
