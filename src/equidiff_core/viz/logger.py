"""``RerunLogger``: one method per message kind, and the entity layout it logs.

The entity paths, the entity layout (which message goes where), the default blueprint, ``VizConfig`` and
``open_recording`` live in ``recording_setup``.

Time: every entity is logged on the ``ros_time`` timeline at the message's header stamp
(falling back to the arrival/recording time when a publisher left the stamp at zero), plus
``episode`` (sequence) and ``episode_time`` (since the episode's first message) for bags.

Bad messages are dropped and counted in ``errors`` (with the last reason in
``last_error``); they never stop the visualisation.
"""

from __future__ import annotations

import collections
import re
import time
from typing import Any

import numpy as np

from .. import geometry
from ..cameras.color import ImageError, compressed_format
from ..config import LabConfig
from ..wire import topics
from ..wire.chunk import ChunkError, chunk_from_msg
from ..wire.pointcloud import CloudError, _structured, msg_to_cloud
from ..wire.rosmsg import (
    MessageError,
    diagnostic_entries,
    doubt_from_msg,
    gripper_width_from_joint_state,
    has_gripper_joints,
    pos_quat_from_msg,
    pose_from_transform,
    stamp_to_ns,
    uint8_buffer,
)
from .recording_setup import (
    BASE,
    CAMERAS,
    CHUNK,
    DIAGNOSTICS,
    DOUBT,
    EE,
    EE_TRAIL,
    EPISODE_INFO,
    EXECUTED,
    EXECUTED_TRAIL,
    GRIPPER_WIDTH,
    IMAGES,
    LATENCY,
    OBS_AGE,
    VOXELS,
    WORKSPACE,
    WORLD,
    VizConfig,
)
from .rerun_sdk import require_rerun

# the first bytes of each compressed format rerun's EncodedImage decodes
_MAGIC = {"jpeg": (b"\xff\xd8\xff", "image/jpeg"), "png": (b"\x89PNG", "image/png")}

# Diagnostic keys with a place of their own in the blueprint; every other number goes to diagnostics/.
_DIAGNOSTIC_ENTITIES = {
    "inference_ms": f"{LATENCY}/inference",
    "obs_to_cmd_ms": f"{LATENCY}/obs_to_cmd",
    "observation_age_ms": f"{OBS_AGE}/policy",
}
OPTICAL_SUFFIX = "_color_optical_frame"

EE_COLOR = (40, 160, 255)
CHUNK_COLOR = (255, 140, 0)
EXECUTED_COLOR = (60, 200, 60)


def _stamp(msg: Any, fallback_ns: int | None) -> int:
    stamp = stamp_to_ns(msg.header.stamp)
    if stamp > 0:
        return stamp
    return int(fallback_ns) if fallback_ns is not None else time.time_ns()


class _Trail:
    """Positions of the last ``span_ns`` (by message time)."""

    def __init__(self, span_ns: int):
        self.span_ns = span_ns
        self.items: collections.deque[tuple[int, np.ndarray]] = collections.deque()

    def add(self, t_ns: int, pos: np.ndarray) -> np.ndarray:
        if self.items and t_ns < self.items[-1][0]:
            self.items.clear()  # time went backwards (new episode, replayed bag): start over
        self.items.append((t_ns, pos))
        while self.items and self.items[0][0] < t_ns - self.span_ns:
            self.items.popleft()
        return np.array([p for _, p in self.items])

    def clear(self) -> None:
        self.items.clear()


class _Throttle:
    """Lets events through at ``hz`` on average, by message time, per key.

    Due times advance by exactly one period (not from the last accepted event), so 50 Hz
    input throttled to 20 Hz gives 20 Hz, not every third message (16.7 Hz).
    """

    def __init__(self, hz: float):
        self.period_ns = int(1e9 / hz)
        self.due: dict[str, tuple[int, int]] = {}  # key -> (last accepted, next due)

    def ready(self, key: str, t_ns: int) -> bool:
        state = self.due.get(key)
        if state is not None:
            last, due = state
            if last <= t_ns < due:
                return False
            if t_ns >= last:  # on schedule; if far behind (a gap in the data), restart from now
                self.due[key] = (t_ns, due + self.period_ns if t_ns < due + self.period_ns else t_ns + self.period_ns)
                return True
        self.due[key] = (t_ns, t_ns + self.period_ns)  # first event, or time went backwards (new episode)
        return True

    def clear(self) -> None:
        self.due.clear()


class RerunLogger:
    """Logs the project's messages (rclpy or rosbags) to one rerun recording stream."""

    def __init__(self, recording: Any, lab: LabConfig, config: VizConfig = VizConfig()):
        self.rr = require_rerun()
        self.rec = recording
        self.lab = lab
        self.config = config
        self.logged: collections.Counter[str] = collections.Counter()
        self.errors: collections.Counter[str] = collections.Counter()
        self.last_error: str | None = None
        self._episode_start_ns: int | None = None
        self._ee_trail = _Trail(int(config.trail_s * 1e9))
        self._executed_trail = _Trail(int(config.trail_s * 1e9))
        self._pose_throttle = _Throttle(config.ee_hz)
        self._cloud_throttle = _Throttle(config.cloud_hz)
        self._camera_names = {cam.frame_id: cam.name for cam in lab.cameras}
        self._static_cameras = True
        self._voxel_size_checked = False
        self.warnings: list[str] = []  # things worth telling the user once (printed by `equidiff viz`)

    # --- time -----------------------------------------------------------------------------

    def _at(self, stamp_ns: int) -> None:
        self.rec.set_time("ros_time", timestamp=np.datetime64(int(stamp_ns), "ns"))
        if self._episode_start_ns is not None:
            self.rec.set_time("episode_time", duration=np.timedelta64(int(stamp_ns) - self._episode_start_ns, "ns"))

    def begin_episode(self, index: int, start_ns: int, info: dict[str, str] | None = None) -> None:
        """Start episode ``index`` (bags): an ``episode`` sequence, ``episode_time`` from ``start_ns``, fresh trails."""
        self.rec.set_time("episode", sequence=int(index))
        self._episode_start_ns = int(start_ns)
        for trail in (self._ee_trail, self._executed_trail):
            trail.clear()
        self._pose_throttle.clear()
        self._cloud_throttle.clear()
        self._at(start_ns)
        for entity in (CHUNK, EE_TRAIL, EXECUTED_TRAIL):  # the previous episode's intent and trails
            self.rec.log(entity, self.rr.Clear(recursive=entity == CHUNK))
        if not self._static_cameras:  # the configured extrinsics until the bag's /tf_static says otherwise
            for cam in self.lab.cameras:
                self._log_camera_transform(cam.name, cam.extrinsics.matrix())
        lines = [f"# episode {index}"] + [f"- **{k}**: {v}" for k, v in sorted((info or {}).items())]
        self.rec.log(EPISODE_INFO, self.rr.TextDocument("\n".join(lines), media_type="text/markdown"))

    def _drop(self, kind: str, err: Exception) -> bool:
        self.errors[kind] += 1
        self.last_error = f"{kind}: {err}"
        return False

    # --- static scene ---------------------------------------------------------------------

    def log_static_scene(self, static_cameras: bool = True) -> None:
        """View coordinates, base axes, workspace box, voxel box size and the configured camera frames.

        rerun's static data shadows temporal data of the same component, so where a bag's
        ``/tf_static`` may follow (``static_cameras=False``) the camera poses are logged per
        episode by ``begin_episode`` instead; their axes and labels stay static.
        """
        rr = self.rr
        ws = self.lab.workspace
        self.rec.log(WORLD, rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        self.rec.log(BASE, rr.TransformAxes3D(self.config.axis_length * 2), static=True)
        self.rec.log(
            BASE, rr.Points3D([[0, 0, 0]], radii=0.0, labels=[self.lab.base_frame], show_labels=True), static=True
        )
        self.rec.log(
            WORKSPACE,
            rr.Boxes3D(
                centers=[ws.center],
                half_sizes=[[ws.edge / 2] * 3],
                colors=[(150, 150, 150)],
                labels=["workspace"],
                show_labels=False,
            ),
            static=True,
        )
        half = ws.voxel_size / 2
        fill = rr.components.FillMode.Solid if self.config.solid_voxels else rr.components.FillMode.MajorWireframe
        # Sizes once, static: per frame only centres and colours travel (10k voxels ~ 150 kB).
        self.rec.log(VOXELS, rr.Boxes3D.from_fields(half_sizes=[[half, half, half]], fill_mode=fill), static=True)
        for ee_like, length in ((EE, self.config.axis_length), (EXECUTED, self.config.axis_length / 2)):
            self.rec.log(ee_like, rr.TransformAxes3D(length), static=True)
        self._static_cameras = static_cameras
        for cam in self.lab.cameras:
            entity = f"{CAMERAS}/{cam.name}"
            self.rec.log(entity, rr.TransformAxes3D(self.config.axis_length), static=True)
            self.rec.log(
                f"{entity}/label", rr.Points3D([[0, 0, 0]], radii=0.0, labels=[cam.name], show_labels=True), static=True
            )
            if static_cameras:
                self._log_camera_transform(cam.name, cam.extrinsics.matrix(), static=True)

    def _log_camera_transform(self, name: str, T: np.ndarray, static: bool = False) -> None:
        p, q = geometry.pos_quat_from_pose(T)
        self.rec.log(
            f"{CAMERAS}/{name}",
            self.rr.Transform3D(translation=p, quaternion=self.rr.Quaternion(xyzw=q)),
            static=static,
        )

    # --- one method per message kind ------------------------------------------------------

    def log_tf(self, msg: Any, receive_ns: int | None = None) -> bool:
        """tf2_msgs/TFMessage (``/tf_static``): camera optical frames under world/cameras, others under world/frames."""
        try:
            any_logged = False
            for tf in msg.transforms:
                T = pose_from_transform(tf)
                child = str(tf.child_frame_id)
                self._at(_stamp(tf, receive_ns))
                if child in self._camera_names or child.endswith(OPTICAL_SUFFIX):
                    name = self._camera_names.get(child, child[: -len(OPTICAL_SUFFIX)])
                    self._log_camera_transform(name, T)
                else:
                    p, q = geometry.pos_quat_from_pose(T)
                    self.rec.log(
                        f"{WORLD}/frames/{child}",
                        self.rr.Transform3D(translation=p, quaternion=self.rr.Quaternion(xyzw=q)),
                    )
                any_logged = True
            self.logged["tf"] += any_logged
            return any_logged
        except (geometry.GeometryError, ValueError) as err:
            return self._drop("tf", err)

    def log_voxels(self, msg: Any, receive_ns: int | None = None) -> bool:
        """Occupied-voxel PointCloud2 (``/voxels``) -> coloured boxes; the age on arrival as a time series."""
        try:
            cloud = msg_to_cloud(msg)
        except CloudError as err:
            if int(msg.width) * int(msg.height) == 0:  # an empty scene is valid: show nothing
                cloud = None
            else:
                return self._drop("voxels", err)
        if cloud is not None and not self._voxel_size_checked:
            self._check_voxel_size(msg, cloud.points)
        stamp = _stamp(msg, receive_ns)
        self._at(stamp)
        if cloud is None:
            self.rec.log(VOXELS, self.rr.Boxes3D.from_fields(centers=np.zeros((0, 3), np.float32)))
        else:
            self.rec.log(VOXELS, self.rr.Boxes3D.from_fields(centers=cloud.points, colors=cloud.colors))
        if receive_ns is not None and stamp_to_ns(msg.header.stamp) > 0:
            self.rec.log(f"{OBS_AGE}/voxels_on_arrival", self.rr.Scalars((receive_ns - stamp) / 1e6))
        self.logged["voxels"] += 1
        return True

    def _check_voxel_size(self, msg: Any, centers: np.ndarray) -> None:
        """Box size from the message itself (centre x against index i): a bag recorded with another
        lab.yaml would otherwise show boxes with gaps or overlaps."""
        try:
            i = _structured(msg, ("i",))[0]["i"].astype(np.int64)
        except CloudError:
            return
        if len(i) < 2 or i.min() == i.max():
            return  # undetermined yet: try the next frame
        self._voxel_size_checked = True
        lo, hi = int(np.argmin(i)), int(np.argmax(i))
        size = float(centers[hi, 0] - centers[lo, 0]) / float(i[hi] - i[lo])
        configured = self.lab.workspace.voxel_size
        if abs(size - configured) > 0.01 * configured:
            self.warnings.append(
                f"/voxels encode {size * 1e3:.2f} mm voxels but the lab config says "
                f"{configured * 1e3:.2f} mm: drawing the message's size"
            )
            self.rec.log(VOXELS, self.rr.Boxes3D.from_fields(half_sizes=[[size / 2] * 3]), static=True)

    def log_camera_cloud(self, camera: str, msg: Any, receive_ns: int | None = None) -> bool:
        """Raw camera PointCloud2 in its optical frame, throttled to ``cloud_hz`` and strided to ``max_cloud_points``."""
        stamp = _stamp(msg, receive_ns)
        if not self._cloud_throttle.ready(camera, stamp):
            return False
        try:
            cloud = msg_to_cloud(msg, drop_invalid=True)  # realsense clouds carry NaN holes
        except CloudError as err:
            return self._drop("clouds", err)
        stride = max(1, -(-len(cloud.points) // self.config.max_cloud_points))
        self._at(stamp)
        self.rec.log(
            f"{CAMERAS}/{camera}/points",
            self.rr.Points3D(cloud.points[::stride], colors=cloud.colors[::stride], radii=0.001),
        )
        self.logged["clouds"] += 1
        return True

    def log_image(self, camera: str, msg: Any, receive_ns: int | None = None) -> bool:
        """CompressedImage (JPEG/PNG) -> ``EncodedImage`` under images/<camera>: the bytes as recorded, no re-encoding."""
        try:
            kind = compressed_format(msg)
            data = uint8_buffer(msg.data).tobytes()
            magic, media_type = _MAGIC[kind]
            if not data.startswith(magic):
                raise ImageError(f"{msg.format!r} image whose {len(data)} bytes are not {kind}")
        except ImageError as err:
            return self._drop("images", err)
        self._at(_stamp(msg, receive_ns))
        self.rec.log(f"{IMAGES}/{camera}", self.rr.EncodedImage(contents=data, media_type=media_type))
        self.logged["images"] += 1
        return True

    def log_ee_pose(self, msg: Any, receive_ns: int | None = None) -> bool:
        """PoseStamped TCP pose -> transform + axes and a trail, at most ``ee_hz``."""
        stamp = _stamp(msg, receive_ns)
        if not self._pose_throttle.ready("ee", stamp):
            return False
        try:
            pos, quat = pos_quat_from_msg(msg)
        except MessageError as err:
            return self._drop("ee_pose", err)
        self._at(stamp)
        self.rec.log(EE, self.rr.Transform3D(translation=pos, quaternion=self.rr.Quaternion(xyzw=quat)))
        trail = self._ee_trail.add(stamp, pos)
        self.rec.log(EE_TRAIL, self.rr.LineStrips3D([trail], colors=[EE_COLOR], radii=0.002))
        self.logged["ee_pose"] += 1
        return True

    def log_joint_states(self, msg: Any, receive_ns: int | None = None) -> bool:
        """JointState -> measured gripper width (sum of the two finger joints), at most ``ee_hz``."""
        try:
            if not has_gripper_joints(msg):
                return False  # arm-only joint states carry no gripper
            stamp = _stamp(msg, receive_ns)
            if not self._pose_throttle.ready("joints", stamp):
                return False
            width = gripper_width_from_joint_state(msg)
        except MessageError as err:
            return self._drop("joint_states", err)
        self._at(stamp)
        self.rec.log(f"{GRIPPER_WIDTH}/measured", self.rr.Scalars(width))
        self.logged["joint_states"] += 1
        return True

    def log_chunk(self, msg: Any, receive_ns: int | None = None) -> bool:
        """MultiDOFJointTrajectory pose chunk -> path, steps labelled with width, one finger-span segment per step."""
        try:
            chunk = chunk_from_msg(msg)
        except ChunkError as err:
            return self._drop("chunk", err)
        stamp = chunk.stamp_ns if chunk.stamp_ns > 0 else (receive_ns or time.time_ns())
        self._at(stamp)
        labels = [
            f"t+{(t - chunk.stamp_ns) / 1e9:.1f}s w={w * 1000:.0f}mm" for t, w in zip(chunk.times_ns, chunk.widths)
        ]
        log_pose_path(self.rec, CHUNK, chunk.poses, chunk.widths, CHUNK_COLOR, labels)
        self.rec.log(f"{GRIPPER_WIDTH}/commanded", self.rr.Scalars(float(chunk.widths[0])))
        self.logged["chunk"] += 1
        return True

    def log_executed_target(self, msg: Any, receive_ns: int | None = None) -> bool:
        """PoseStamped target franka_node actually sent -> transform + trail, at most ``ee_hz``."""
        stamp = _stamp(msg, receive_ns)
        if not self._pose_throttle.ready("executed", stamp):
            return False
        try:
            pos, quat = pos_quat_from_msg(msg)
        except MessageError as err:
            return self._drop("executed_target", err)
        self._at(stamp)
        self.rec.log(EXECUTED, self.rr.Transform3D(translation=pos, quaternion=self.rr.Quaternion(xyzw=quat)))
        trail = self._executed_trail.add(stamp, pos)
        self.rec.log(EXECUTED_TRAIL, self.rr.LineStrips3D([trail], colors=[EXECUTED_COLOR], radii=0.0015))
        self.logged["executed_target"] += 1
        return True

    def log_doubt(self, msg: Any, receive_ns: int | None = None) -> bool:
        """Vector3Stamped doubt of a chunk (``wire.rosmsg.doubt_msg``) -> one time series per signal, at the chunk's stamp."""
        try:
            doubt = doubt_from_msg(msg)
        except MessageError as err:
            return self._drop("doubt", err)
        self._at(doubt.stamp_ns if doubt.stamp_ns > 0 else (receive_ns or time.time_ns()))
        count = 0
        for name, value in (("disagreement", doubt.disagreement_m), ("spread", doubt.spread_m)):
            if np.isfinite(value):  # NaN: not computed for this chunk
                self.rec.log(f"{DOUBT}/{name}", self.rr.Scalars(value))
                count += 1
        self.logged["doubt"] += 1
        return count > 0

    def log_diagnostics(self, msg: Any, receive_ns: int | None = None) -> bool:
        """DiagnosticArray -> one time series per numeric key (latency and observation age in their own views)."""
        try:
            entries = diagnostic_entries(msg)
        except MessageError as err:
            return self._drop("diagnostics", err)
        self._at(_stamp(msg, receive_ns))
        count = 0
        for entry in entries:
            prefix = f"{DIAGNOSTICS}/{_entity_part(entry.name or 'unnamed')}"
            for key in entry.values:
                value = entry.number(key)
                if value is None:  # text values (e.g. "ok") and NaN have no time series
                    continue
                entity = _DIAGNOSTIC_ENTITIES.get(key, f"{prefix}/{_entity_part(key)}")
                self.rec.log(entity, self.rr.Scalars(value))
                count += 1
        self.logged["diagnostics"] += 1
        return count > 0

    # --- dispatch by topic (bags and the live node share it) -------------------------------

    def log_message(self, topic: str, msg: Any, receive_ns: int | None = None) -> bool:
        """Route one message by its topic (architecture.md); unknown topics are ignored (False)."""
        handler = self._handlers().get(topic)
        if handler is not None:
            return handler(msg, receive_ns)
        camera = topics.camera_of_color_topic(topic)
        if camera is not None:
            return self.log_image(camera, msg, receive_ns) if self.config.images else False
        if topic.startswith(topics.CAMERA_TOPIC_PREFIX) and topic.endswith("/points"):
            if not self.config.clouds:
                return False
            return self.log_camera_cloud(topic.split("/")[2], msg, receive_ns)
        return False

    def _handlers(self) -> dict[str, Any]:
        return {
            topics.TOPIC_VOXELS: self.log_voxels,
            topics.TOPIC_EE_POSE: self.log_ee_pose,
            topics.TOPIC_JOINT_STATES: self.log_joint_states,
            topics.TOPIC_COMMAND_CHUNK: self.log_chunk,
            topics.TOPIC_EXECUTED_TARGET: self.log_executed_target,
            topics.TOPIC_DIAGNOSTICS: self.log_diagnostics,
            topics.TOPIC_POLICY_DOUBT: self.log_doubt,
            topics.TOPIC_TF_STATIC: self.log_tf,
        }


def log_pose_path(
    rec: Any,
    entity: str,
    poses: np.ndarray,
    widths: np.ndarray,
    color: tuple[int, int, int],
    labels: list[str] | None = None,
) -> None:
    """A pose sequence as ``<entity>/path`` (line), ``/steps`` (points, fading with time, labelled) and
    ``/gripper`` (one segment per step along the TCP y axis, as long as the gripper opening)."""
    rr = require_rerun()
    positions = poses[:, :3, 3]
    half = (np.asarray(widths, dtype=np.float64) / 2)[:, None] * poses[:, :3, 1]  # fingers close along TCP y
    fade = np.linspace(1.0, 0.35, len(poses))[:, None]
    colors = (np.asarray(color, dtype=np.float64)[None, :] * fade).astype(np.uint8)
    rec.log(f"{entity}/path", rr.LineStrips3D([positions], colors=[color], radii=0.0015))
    rec.log(f"{entity}/steps", rr.Points3D(positions, colors=colors, radii=0.004, labels=labels, show_labels=False))
    rec.log(
        f"{entity}/gripper",
        rr.LineStrips3D(np.stack([positions - half, positions + half], axis=1), colors=colors, radii=0.001),
    )


def _entity_part(name: str) -> str:
    """A diagnostic status name ('policy_node: inference') as one entity-path part."""
    return re.sub(r"[^A-Za-z0-9_-]+", "_", name).strip("_") or "unnamed"


TOPICS_HANDLED = (
    topics.TOPIC_VOXELS,
    topics.TOPIC_EE_POSE,
    topics.TOPIC_JOINT_STATES,
    topics.TOPIC_COMMAND_CHUNK,
    topics.TOPIC_EXECUTED_TARGET,
    topics.TOPIC_DIAGNOSTICS,
    topics.TOPIC_POLICY_DOUBT,
    topics.TOPIC_TF_STATIC,
)
