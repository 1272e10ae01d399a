"""Data-area test helpers: a synthetic pick episode written through the recorder's EpisodeWriter,
and a small rclpy harness for the live-node tests.

Used by the data tests and to (re)generate the sample bag under bags/:

    python test/helpers_data.py bags/sample_pick_0000

Scene: a table patch and a 4 cm cube in the workspace; the TCP starts above the cube,
descends, closes the gripper, and lifts the cube. The voxel grid shows the table, the cube
(moving with the gripper once grasped) and two finger blobs. /franka/ee_pose and
/franka/joint_states at ``state_hz``, one-point teleop chunks on /franka/command_chunk at
``command_hz`` leading the measured pose by ``lag_s`` (the arm lags its targets), /voxels at
``obs_hz``, each lab camera's JPEG colour image on /cameras/<name>/color/image_raw/compressed
at the same instants (the grid's occupied voxels splatted through a pinhole at the camera's
configured pose: a picture of the same scene, small enough for the sample bag),
/spacenav/joy with the operator's input, /tf_static from the lab config.
"""

from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT / "src") not in sys.path:
    sys.path.insert(0, str(ROOT / "src"))

from equidiff_core import geometry
from equidiff_core.cameras.color import color_image_msg
from equidiff_core.config import Workspace, load_lab_config
from equidiff_core.data.bags import EpisodeMeta
from equidiff_core.data.recording import EpisodeWriter, RecordingConfig
from equidiff_core.wire.chunk import PoseChunk, chunk_to_msg
from equidiff_core.wire.pointcloud import grid_to_voxel_msg
from equidiff_core.wire.rosmsg import NS_PER_S, rosbags_factory
from equidiff_core.wire.topics import (
    COMPRESSED_IMAGE_TYPE,
    TOPIC_POLICY_STATE,
    TOPIC_TELEOP_ACTIVE,
    camera_color_topic,
)

LAB = load_lab_config(ROOT / "config" / "lab.yaml")
T0_NS = 1_700_000_000 * NS_PER_S  # a fixed wall-clock start: deterministic bags
OPEN_W, CLOSED_W = 0.08, 0.038
DOWN = np.array([[1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]])  # TCP z pointing down


@dataclass(frozen=True)
class SyntheticEpisode:
    duration_s: float = 8.0
    obs_hz: float = 5.0
    state_hz: float = 50.0
    command_hz: float = 10.0
    lag_s: float = 0.1
    cube_xy: tuple[float, float] = (0.47, 0.03)
    yaw: float = 0.3  # cube (and grasp) yaw, rad
    t0_ns: int = T0_NS
    image_size: tuple[int, int] | None = (212, 120)  # colour images (width, height); None: none recorded
    image_hfov_deg: float = 90.0  # a D455's colour field of view


def command_at(ep: SyntheticEpisode, t: float) -> tuple[np.ndarray, float]:
    """Commanded TCP pose and gripper width at time t (s): approach, descend, grasp, lift."""
    cx, cy = ep.cube_xy
    T = ep.duration_s
    above, grasp_z, lift_z = 0.30, 0.02 + 0.02, 0.22

    def smooth(a, b, s):
        s = min(max(s, 0.0), 1.0)
        return a + (b - a) * (0.5 - 0.5 * math.cos(math.pi * s))

    start = np.array([cx - 0.08, cy - 0.06, above])
    hover = np.array([cx, cy, above])
    if t < 0.3 * T:
        p = smooth(start, hover, t / (0.3 * T))
        yaw = smooth(0.0, ep.yaw, t / (0.3 * T))
    elif t < 0.55 * T:
        p = smooth(hover, np.array([cx, cy, grasp_z]), (t - 0.3 * T) / (0.25 * T))
        yaw = ep.yaw
    elif t < 0.65 * T:
        p, yaw = np.array([cx, cy, grasp_z]), ep.yaw
    else:
        p = smooth(np.array([cx, cy, grasp_z]), np.array([cx, cy, lift_z]), (t - 0.65 * T) / (0.35 * T))
        yaw = ep.yaw
    width = OPEN_W if t < 0.58 * T else CLOSED_W
    R = geometry.rotz(yaw) @ DOWN
    return geometry.make_pose(R, p), width


def measured_at(ep: SyntheticEpisode, t: float) -> tuple[np.ndarray, float]:
    return command_at(ep, max(0.0, t - ep.lag_s))


def voxel_grid(ep: SyntheticEpisode, ws: Workspace, t: float) -> np.ndarray:
    R = ws.resolution
    grid = np.zeros((4, R, R, R), dtype=np.uint8)
    lower, size = ws.lower, ws.voxel_size

    def fill(lo, hi, rgb):
        a = np.clip(np.floor((np.asarray(lo) - lower) / size).astype(int), 0, R)
        b = np.clip(np.ceil((np.asarray(hi) - lower) / size).astype(int), 0, R)
        if np.any(b <= a):
            return
        sl = (slice(a[0], b[0]), slice(a[1], b[1]), slice(a[2], b[2]))
        grid[0][sl] = 255
        for c in range(3):
            grid[1 + c][sl] = rgb[c]

    cx, cy = ep.cube_xy
    # table top (a patch, so the sample bag stays small)
    fill((cx - 0.12, cy - 0.12, -0.005), (cx + 0.12, cy + 0.12, 0.0), (150, 120, 90))
    pose, width = measured_at(ep, t)
    tcp = pose[:3, 3]
    grasped = t >= 0.6 * ep.duration_s
    cube_c = np.array([tcp[0], tcp[1], tcp[2]]) if grasped else np.array([cx, cy, 0.02])
    fill(cube_c - 0.02, cube_c + 0.02, (200, 30, 30))
    side = pose[:3, 1]  # fingers open along the TCP y axis
    for s in (-1, 1):
        f = tcp + s * side * width / 2 + np.array([0, 0, 0.02])
        fill(f - [0.008, 0.008, 0.02], f + [0.008, 0.008, 0.02], (60, 60, 60))
    return grid


def camera_image(grid: np.ndarray, ws: Workspace, T_base_optical: np.ndarray, size, hfov_deg: float) -> np.ndarray:
    """RGB (H, W, 3) of the grid's occupied voxels seen by a pinhole camera at ``T_base_optical``
    (far voxels drawn first, each a square as wide as the voxel), over a plain backdrop."""
    w, h = size
    f = (w / 2) / math.tan(math.radians(hfov_deg) / 2)
    image = np.empty((h, w, 3), np.uint8)
    image[:] = np.linspace(90, 160, h, dtype=np.uint8)[:, None, None]  # a backdrop brighter towards the floor
    idx = np.argwhere(grid[0] > 0)
    if len(idx) == 0:
        return image
    centres = ws.lower + (idx + 0.5) * ws.voxel_size
    colours = grid[1:, idx[:, 0], idx[:, 1], idx[:, 2]].T
    T = np.linalg.inv(T_base_optical)
    p = centres @ T[:3, :3].T + T[:3, 3]
    ahead = p[:, 2] > 0.05
    p, colours = p[ahead], colours[ahead]
    order = np.argsort(-p[:, 2])  # painter's order: far first, near last wins
    p, colours = p[order], colours[order]
    u = f * p[:, 0] / p[:, 2] + w / 2
    v = f * p[:, 1] / p[:, 2] + h / 2
    half = np.maximum(1, np.ceil(f * ws.voxel_size / p[:, 2] / 2)).astype(int)
    for dv in range(-half.max(), half.max() + 1):
        for du in range(-half.max(), half.max() + 1):
            sel = (abs(du) <= half) & (abs(dv) <= half)
            uu, vv = (u[sel] + du).astype(int), (v[sel] + dv).astype(int)
            inside = (uu >= 0) & (uu < w) & (vv >= 0) & (vv < h)
            image[vv[inside], uu[inside]] = colours[sel][inside]
    return image


def write_synthetic_episode(
    path: str | Path,
    ep: SyntheticEpisode = SyntheticEpisode(),
    meta: EpisodeMeta | None = None,
    ws: Workspace | None = None,
    config: RecordingConfig = RecordingConfig(min_free_gib=0.0),
    policy_states: tuple[tuple[float, str], ...] = (),
    teleop_active: tuple[tuple[float, bool], ...] = (),
) -> Path:
    """A demonstration, or with ``policy_states`` ((t, "running" | "paused <reason>"), ...) and ``teleop_active``
    ((t, bool), ...) a policy's roll-out that the operator corrected, as policy_node and teleop_node latch them."""
    ws = ws or LAB.workspace
    f = rosbags_factory()
    meta = meta or EpisodeMeta(
        task="pick_cube", operator="synthetic", success=True, notes="synthetic episode (test/helpers_data.py)", seed=0
    )
    frame = LAB.base_frame
    events: list[tuple[int, str, object]] = []
    ns = lambda s: ep.t0_ns + round(s * NS_PER_S)
    n_state = int(ep.duration_s * ep.state_hz)
    for i in range(n_state):
        t = i / ep.state_hz
        pose, width = measured_at(ep, t)
        p, q = geometry.pos_quat_from_pose(pose)
        msg = f.make(
            "geometry_msgs/msg/PoseStamped",
            header=f.header(ns(t), frame),
            pose=f.make(
                "geometry_msgs/msg/Pose",
                position=f.make("geometry_msgs/msg/Point", x=p[0], y=p[1], z=p[2]),
                orientation=f.make("geometry_msgs/msg/Quaternion", x=q[0], y=q[1], z=q[2], w=q[3]),
            ),
        )
        events.append((ns(t) + 300_000, "/franka/ee_pose", msg))
        names = [f"fr3_joint{j}" for j in range(1, 8)] + ["fr3_finger_joint1", "fr3_finger_joint2"]
        js = f.make(
            "sensor_msgs/msg/JointState",
            header=f.header(ns(t), ""),
            name=names,
            position=f.float64_array([0.0, -0.78, 0.0, -2.36, 0.0, 1.57, 0.78, width / 2, width / 2]),
            velocity=f.float64_array([]),
            effort=f.float64_array([]),
        )
        events.append((ns(t) + 300_000, "/franka/joint_states", js))
    n_cmd = int(ep.duration_s * ep.command_hz)
    for i in range(n_cmd):
        t = i / ep.command_hz
        pose, width = command_at(ep, t)
        chunk = PoseChunk(ns(t), np.array([ns(t)], dtype=np.int64), pose[None], np.array([width]))
        events.append((ns(t) + 500_000, "/franka/command_chunk", chunk_to_msg(chunk, f, frame)))
        prev = command_at(ep, max(0.0, t - 1 / ep.command_hz))[0]
        v = (pose[:3, 3] - prev[:3, 3]) * ep.command_hz / 0.1  # as a SpaceMouse deflection
        joy = f.make(
            "sensor_msgs/msg/Joy",
            header=f.header(ns(t), ""),
            axes=np.clip(np.array([v[0], v[1], v[2], 0, 0, 0], dtype=np.float32), -1, 1),
            buttons=np.array([int(width < OPEN_W), 0], dtype=np.int32),
        )
        events.append((ns(t) + 200_000, "/spacenav/joy", joy))
    n_obs = int(ep.duration_s * ep.obs_hz)
    for i in range(n_obs):
        t = i / ep.obs_hz
        grid = voxel_grid(ep, ws, t)
        msg = grid_to_voxel_msg(grid, ws.lower, ws.voxel_size, ns(t), frame, f)
        events.append((ns(t) + 40_000_000, "/voxels", msg))  # voxelising takes ~40 ms
        for cam in LAB.cameras if ep.image_size else ():
            rgb = camera_image(grid, ws, cam.extrinsics.matrix(), ep.image_size, ep.image_hfov_deg)
            image = color_image_msg(rgb, ns(t), cam.frame_id, f)
            events.append((ns(t) + 10_000_000, camera_color_topic(cam.name), image))  # published with the cloud
    for t, state in policy_states:
        events.append((ns(t), TOPIC_POLICY_STATE, f.make("std_msgs/msg/String", data=state)))
    for t, active in teleop_active:
        events.append((ns(t), TOPIC_TELEOP_ACTIVE, f.make("std_msgs/msg/Bool", data=active)))
    events.sort(key=lambda e: e[0])
    with EpisodeWriter(path, meta, config) as writer:
        writer.write_tf_static(LAB, ep.t0_ns)
        for stamp, topic, msg in events:
            writer.write(topic, msg, stamp, COMPRESSED_IMAGE_TYPE if topic.endswith("/compressed") else None)
    return Path(path)


# --- live-ROS test helpers (rclpy imported lazily) ------------------------------------------


class RosHarness:
    """An rclpy node in its own context, spun on demand."""

    def __init__(self):
        import rclpy
        from rclpy.executors import SingleThreadedExecutor

        from equidiff_core.wire.rosmsg import RclpyFactory

        self.rclpy = rclpy
        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx)
        self.node = rclpy.create_node("data_test_harness", context=self.ctx)
        self.executor = SingleThreadedExecutor(context=self.ctx)
        self.executor.add_node(self.node)
        self.f = RclpyFactory()

    def spin_until(self, cond, timeout: float, period: float = 0.02) -> bool:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            self.executor.spin_once(timeout_sec=period)
            if cond():
                return True
        return False

    def spin_for(self, seconds: float) -> None:
        self.spin_until(lambda: False, seconds)

    def close(self):
        self.executor.shutdown()
        self.node.destroy_node()
        self.rclpy.shutdown(context=self.ctx)


def decoded(raw: bytes, msgtype: str):
    """Decode CDR with rosbags (an independent reader of what rclpy/DDS produced)."""
    return rosbags_factory().typestore.deserialize_cdr(raw, msgtype)


def assert_same(a, b, where="msg"):
    """Field-by-field equality of a rosbags message ``a`` and an rclpy (or rosbags) message ``b``."""
    if hasattr(a, "__dataclass_fields__"):
        assert type(a).__name__.split("__")[-1] == type(b).__name__, where
        for name in a.__dataclass_fields__:
            if name != "__msgtype__":
                assert_same(getattr(a, name), getattr(b, name), f"{where}.{name}")
    elif isinstance(a, np.ndarray):
        np.testing.assert_array_equal(a, np.asarray(b, dtype=a.dtype), err_msg=where)
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b)):
            assert_same(x, y, f"{where}[{i}]")
    else:
        assert a == b, f"{where}: {a!r} != {b!r}"


if __name__ == "__main__":
    out = write_synthetic_episode(sys.argv[1] if len(sys.argv) > 1 else ROOT / "bags" / "sample_pick_0000")
    print(out)
