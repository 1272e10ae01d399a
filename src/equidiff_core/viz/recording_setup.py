"""Where the visualisation goes and how it is laid out: the entity paths, the default blueprint,
``config/viz.yaml`` (``VizConfig``) and ``open_recording`` (a spawned viewer, a remote one or an .rrd).

``logger.RerunLogger`` logs the project's messages under these entity paths.

Entity layout (the same live and from bags; the base frame is the world):

| entity | archetype | from |
|---|---|---|
| ``world/base`` | axes of the robot base frame | static |
| ``world/workspace`` | wireframe box of the voxel workspace | lab.yaml |
| ``world/cameras/<name>`` | ``Transform3D`` T_base_optical + axes | lab.yaml (live: static); bags: lab.yaml at the episode start, then the bag's ``/tf_static`` |
| ``world/cameras/<name>/points`` | ``Points3D`` in the optical frame (throttled) | ``/cameras/<name>/points`` |
| ``images/<name>`` | ``EncodedImage``: the camera's JPEG as recorded, decoded by the viewer | ``/cameras/<name>/color/image_raw/compressed`` |
| ``world/voxels`` | ``Boxes3D``: half-sizes once (static), centres + colours per frame | ``/voxels`` |
| ``world/ee`` + ``world/ee_trail`` | TCP ``Transform3D`` + axes; ``LineStrips3D`` of the last ``trail_s`` | ``/franka/ee_pose`` |
| ``world/chunk/{path,steps,gripper}`` | predicted poses as a path; steps labelled with the gripper width; one segment per step as wide as the commanded gripper opening | ``/franka/command_chunk`` |
| ``world/executed_target`` + ``world/executed_trail`` | what franka_node actually sent | ``/franka/executed_target`` |
| ``metrics/latency/{inference,obs_to_cmd}`` | ``Scalars`` ms | ``/diagnostics`` (policy) |
| ``metrics/observation_age/{policy,voxels_on_arrival}`` | ``Scalars`` ms | ``/diagnostics``; voxel stamp vs arrival |
| ``metrics/gripper_width/{measured,commanded}`` | ``Scalars`` m | joint states; chunk step 0 |
| ``metrics/doubt/{disagreement,spread}`` | ``Scalars`` m, at each chunk's stamp | ``/policy/doubt`` |
| ``diagnostics/<status>/<key>`` | ``Scalars`` of every other numeric diagnostic | ``/diagnostics`` |
| ``episode/info`` | ``TextDocument`` of the bag's episode metadata | bag ``custom_data`` |
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..config import bounded, default_config_dir, from_dict, load_mapping
from .rerun_sdk import require_rerun

APPLICATION_ID = "equidiff_ros"

WORLD = "world"
BASE = "world/base"
WORKSPACE = "world/workspace"
CAMERAS = "world/cameras"
VOXELS = "world/voxels"
EE = "world/ee"
EE_TRAIL = "world/ee_trail"
CHUNK = "world/chunk"
EXECUTED = "world/executed_target"
EXECUTED_TRAIL = "world/executed_trail"
LATENCY = "metrics/latency"
OBS_AGE = "metrics/observation_age"
GRIPPER_WIDTH = "metrics/gripper_width"
DOUBT = "metrics/doubt"
DIAGNOSTICS = "diagnostics"
EPISODE_INFO = "episode/info"
IMAGES = "images"


@dataclass(frozen=True)
class VizConfig:
    """What to show and how often (config/viz.yaml)."""

    # TCP pose, executed target and their trails (state arrives at >= 100 Hz)
    ee_hz: float = bounded(20.0, unit="Hz", gt=0, le=1000)
    trail_s: float = bounded(5.0, unit="s", gt=0, le=600)  # length of the TCP / executed-target trails
    clouds: bool = False  # also show the raw camera clouds (costs bandwidth: ~5 MB per cloud)
    images: bool = True  # the cameras' colour images (JPEG, logged as recorded: tens of kB each)
    cloud_hz: float = bounded(1.0, unit="Hz", gt=0, le=100)  # per camera
    # clouds are strided down to at most this many points
    max_cloud_points: int = bounded(50_000, unit="points", ge=1, le=10_000_000)
    solid_voxels: bool = True  # filled boxes (False: wireframe)
    axis_length: float = bounded(0.05, unit="m", gt=0, le=1)  # TCP / camera / base axes

    def __post_init__(self):
        for name in ("ee_hz", "trail_s", "cloud_hz", "axis_length"):
            if getattr(self, name) <= 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        if self.max_cloud_points < 1:
            raise ValueError(f"max_cloud_points must be >= 1, got {self.max_cloud_points}")


def load_viz_config(path: str | Path | None = None) -> VizConfig:
    """config/viz.yaml (or ``path``) -> VizConfig; defaults when the default file is absent."""
    if path is None:
        path = default_config_dir() / "viz.yaml"
        if not Path(path).is_file():
            return VizConfig()
    return from_dict(VizConfig, load_mapping(path), where=Path(path).name)


def default_blueprint(cameras: tuple[str, ...] | list[str] = ()) -> Any:
    """3D scene on the left (with a row of camera images below it, one per name in ``cameras``);
    latency, observation age, gripper width, the policy's doubt and other diagnostics on the right."""
    require_rerun()
    import rerun.blueprint as rrb

    scene = rrb.Spatial3DView(name="scene (base frame)", origin=f"/{WORLD}")
    if cameras:
        images = rrb.Horizontal(*[rrb.Spatial2DView(name=c, origin=f"/{IMAGES}/{c}") for c in cameras])
        scene = rrb.Vertical(scene, images, row_shares=[3, 1])
    return rrb.Blueprint(
        rrb.Horizontal(
            scene,
            rrb.Vertical(
                rrb.TimeSeriesView(name="latency (ms)", origin=f"/{LATENCY}"),
                rrb.TimeSeriesView(name="observation age (ms)", origin=f"/{OBS_AGE}"),
                rrb.TimeSeriesView(name="gripper width (m)", origin=f"/{GRIPPER_WIDTH}"),
                rrb.TimeSeriesView(name="doubt (m)", origin=f"/{DOUBT}"),
                rrb.Tabs(
                    rrb.TimeSeriesView(name="diagnostics", origin=f"/{DIAGNOSTICS}"),
                    rrb.TextDocumentView(name="episode", origin="/episode"),
                ),
            ),
            column_shares=[3, 2],
        ),
        rrb.TimePanel(state="expanded", timeline="ros_time"),  # start on header stamps, not log_time
        rrb.SelectionPanel(state="collapsed"),
    )


def open_recording(
    recording_id: str | None = None,
    *,
    spawn: bool = False,
    connect: str | None = None,
    save: str | Path | None = None,
    application_id: str = APPLICATION_ID,
    blueprint: Any = None,
) -> Any:
    """A rerun RecordingStream sending to exactly one sink: a spawned viewer, a remote viewer, or an .rrd file."""
    rr = require_rerun()
    if sum([bool(spawn), connect is not None, save is not None]) != 1:
        raise ValueError("choose exactly one rerun sink: spawn a viewer, connect to ADDR, or save to FILE.rrd")
    blueprint = default_blueprint() if blueprint is None else blueprint
    rec = rr.RecordingStream(application_id, recording_id=recording_id)
    if spawn:
        rec.spawn(default_blueprint=blueprint)
    elif connect is not None:
        rec.connect_grpc(grpc_url(connect), default_blueprint=blueprint)
    else:
        save = Path(save)
        save.parent.mkdir(parents=True, exist_ok=True)
        rec.save(save, default_blueprint=blueprint)
    return rec


def grpc_url(address: str) -> str:
    """'host:port' (or a full rerun+http:// URL) -> the viewer's gRPC proxy URL."""
    if "://" in address:
        return address
    if ":" not in address:
        address = f"{address}:9876"
    return f"rerun+http://{address}/proxy"
