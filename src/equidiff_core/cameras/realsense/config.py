"""Options of the RealSense backend: the ``options`` mapping of a camera in config/lab.yaml."""

from __future__ import annotations

from dataclasses import dataclass

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

    depth_width: int | None = None  # default: the colour width/height (the D455 supports 848x480 for both)
    depth_height: int | None = None
    decimation: int = 1  # 1 = off; 2..8 divides the depth resolution (and noise, and cost)
    spatial: bool = False  # edge-preserving spatial smoothing (in disparity space)
    temporal: bool = False  # temporal smoothing over the last frames (in disparity space)
    hole_filling: bool = False  # fill holes from the nearest valid neighbour
    exposure_us: float | None = None  # colour exposure in microseconds; None = auto
    white_balance_k: float | None = None  # colour white balance in kelvin; None = auto
    depth_exposure_us: float | None = None  # depth sensor exposure; None = auto
    laser_power: float | None = None  # emitter power in mW; None = device default
    visual_preset: str | None = None  # one of VISUAL_PRESETS; None = device default
    reset_after_timeouts: int = (
        3  # consecutive frame timeouts (each the reader's timeout, 1 s in camera_node) before a reset
    )
    reenumerate_timeout_s: float = (
        10.0  # wait this long for the serial to come back after a reset (a D4xx takes a few s)
    )
    reconnect_backoff_s: float = 1.0  # pause before the next reset after a failed one; doubles each time...
    reconnect_backoff_max_s: float = 30.0  # ...up to this

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
