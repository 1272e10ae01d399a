"""Options of the twin camera backend: camera_node's ``backend_options`` mapping (``make_camera("twin", cam, **options)``)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class TwinCameraOptions:
    """Backend options (``make_camera("twin", cam, **options)``); None = take it from config/twin.yaml."""

    width: int | None = None
    height: int | None = None
    depth_noise: bool | None = None
    dropout: float | None = None
    shm_name: str | None = None  # twin state block (default: from ROS_DOMAIN_ID)
    twin_config: object = None  # path of twin.yaml, or a TwinConfig (in-process users)
    paced: bool = True  # read() waits for the next 1/publish_hz wall-clock tick, as a camera waits for frames
    lockstep: bool = False  # simulated time: read() takes the frames the sim requests (overrides paced)
    slot: int = 0  # lockstep: this camera's registration slot in the shared state (its index in lab.yaml)
    # while a file at this path exists, read() delivers no frame and times out, as a RealSense whose
    # USB link stalled does: the safety bench's camera fault, through camera_node's own error path
    stall_flag: str | None = None
