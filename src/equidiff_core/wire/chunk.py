"""Pose chunks: a sequence of absolute TCP targets with gripper widths, each at an absolute time.

The wire format is ``trajectory_msgs/MultiDOFJointTrajectory`` (docs/architecture.md, note 3):
``joint_names = ["fr3_hand_tcp", "gripper"]``, step ``i`` at ``header.stamp +
points[i].time_from_start``, ``transforms[0]`` the TCP pose in the base frame,
``transforms[1].translation.x`` the gripper width. The policy, teleop and the scripted
expert all publish this, and the franka node, recorder, dataset and viz all read it, through
the two functions here.
"""

from __future__ import annotations

import collections
import enum
import math
from dataclasses import dataclass

import numpy as np

from .. import geometry
from .rosmsg import MsgFactory, stamp_to_ns

JOINT_NAMES = ("fr3_hand_tcp", "gripper")


class ChunkReason(enum.StrEnum):
    """Why a chunk was refused: franka_node counts each on /diagnostics (``<reason>_rejected``)."""

    MALFORMED = "malformed"  # empty, arrays that disagree, steps out of order, wrong joint names
    NAN = "nan"  # NaN / inf, a non-unit quaternion, a non-orthonormal rotation
    STALE = "stale"  # every step in the past, the last one too long ago
    FUTURE = "future"  # stamped further ahead of the receiver's clock than allowed
    JUMP = "jump"  # the first live step too far from the robot
    CONE = "cone"  # a step tilted past the orientation cone
    HELD = "held"  # the controller refuses chunks: a stop awaits acknowledgement, or it is homing


class ChunkError(ValueError):
    """A chunk that must not be executed; ``reason`` (a ``ChunkReason``) says which kind of refusal."""

    def __init__(self, message: str, reason: ChunkReason = ChunkReason.MALFORMED):
        super().__init__(message)
        self.reason = ChunkReason(reason)


@dataclass(frozen=True)
class PoseChunk:
    stamp_ns: int  # header stamp: observation time (policy) or command time (teleop)
    times_ns: np.ndarray  # (K,) absolute time of each step, non-decreasing
    poses: np.ndarray  # (K, 4, 4) TCP targets in the base frame
    widths: np.ndarray  # (K,) gripper width targets, metres

    def __post_init__(self):
        validate_chunk(self)

    def __len__(self) -> int:
        return len(self.times_ns)

    @property
    def actions(self) -> np.ndarray:
        """(K, 10) absolute actions."""
        return geometry.pose_to_action(self.poses, self.widths)

    def after(self, t_ns: int) -> PoseChunk | None:
        """The steps strictly later than ``t_ns`` (None if none are left)."""
        keep = self.times_ns > t_ns
        if not keep.any():
            return None
        return PoseChunk(self.stamp_ns, self.times_ns[keep], self.poses[keep], self.widths[keep])


class AnswerSchedule:
    """Which observations the policy answers: one every ``execute_steps`` frames (0: every
    ``n_action_steps``-th, i.e. one per chunk), so each chunk's steps run before the next.

    policy_node and the twin's in-process evaluation both ask it, so the two cannot drift.
    An observation is due once ``execute_steps - 0.5`` frame periods have passed since the last
    answered one: half a period of slack for camera stamps that jitter."""

    def __init__(self, execute_steps: int, n_action_steps: int, dt_ns: int):
        self.steps = int(execute_steps) or int(n_action_steps)
        if not 1 <= self.steps <= n_action_steps:
            raise ValueError(f"execute_steps must be within 1..{n_action_steps} (0: all), got {execute_steps}")
        self.dt_ns = int(dt_ns)
        self.answered_ns: int | None = None  # the last observation answered

    def due(self, stamp_ns: int) -> bool:
        return self.answered_ns is None or stamp_ns - self.answered_ns >= (self.steps - 0.5) * self.dt_ns

    def answer(self, stamp_ns: int) -> None:
        self.answered_ns = int(stamp_ns)

    def restart(self) -> None:
        """Answer the next observation at once (an episode begins)."""
        self.answered_ns = None


class SamplingSeeds:
    """The DDIM noise seed of each answered observation.

    Inside an episode the k-th answered observation (k = 0, 1, ...) gets ``episode_seed * 1000 + k``;
    outside one, a draw from ``rng_seed``'s generator (None: fresh entropy). policy_node (told
    each twin episode's seed on /policy/episode) and the in-process evaluation both take their
    seeds here, so a scene gets the same noise in both: their outcomes then differ only where
    their observations do, not by the luck of the draw."""

    def __init__(self, rng_seed: int | None = None):
        self.rng = np.random.default_rng(rng_seed)
        self.episode_seed: int | None = None
        self.index = 0

    def start_episode(self, episode_seed: int) -> None:
        self.episode_seed, self.index = int(episode_seed), 0

    def next(self) -> int:
        if self.episode_seed is None:
            return int(self.rng.integers(2**31))
        seed = self.episode_seed * 1000 + self.index
        self.index += 1
        return seed


def steps_to_publish(execute_steps: int, latency_s: float, dt_s: float, available: int) -> int:
    """Steps a chunk must carry so it lasts until the next one arrives: the ``execute_steps`` run
    before the next observation is answered, the ``latency_s`` until that one's chunk arrives,
    and one step beyond it to interpolate towards (``execute_steps + ceil(L / dt) + 1``, at most
    the ``available`` predicted steps)."""
    return min(int(available), int(execute_steps) + math.ceil(round(latency_s / dt_s, 6)) + 1)


def bridging_execute_steps(n_action_steps: int, latency_s: float, dt_s: float, available: int) -> int:
    """policy_node's default k (``execute_steps`` 0) while it bridges a latency: all ``n_action_steps``,
    or fewer when L is too long for them (the largest k with k + ceil(L/dt) + 1 <= ``available``:
    the next observation is answered sooner, so its chunk still comes before this one runs out),
    at least 1."""
    return max(1, min(int(n_action_steps), int(available) - math.ceil(round(latency_s / dt_s, 6)) - 1))


def max_bridged_latency_s(execute_steps: int, dt_s: float, available: int) -> float:
    """The longest latency that chunks of at most ``available`` steps still bridge (``steps_to_publish``'s
    inverse): beyond it the arm stands at each chunk's last step until the next chunk arrives."""
    return max(0, int(available) - int(execute_steps) - 1) * float(dt_s)


# policy_node's chunk-execution defaults. The launch files declare the same values as their
# arguments' defaults (test_launch_files.py checks), so a lab launch runs what the node runs.
DEFAULT_EXECUTE_STEPS = 0  # answer one observation per chunk of n_action_steps
DEFAULT_LATENCY_S = "auto"  # measure the observation-to-arrival latency and bridge it
DEFAULT_RTC = False  # real-time chunking
DEFAULT_TRANSPORT_S = 0.01  # publication -> the chunk takes effect at franka_node (LatencyEstimate)
DEFAULT_N_ACTION_STEPS = 0  # steps published: 0 = enough to bridge the latency (or the preset's, latency off)


class LatencyEstimate:
    """The observation-to-arrival latency L that a chunk must bridge: ``latency_s`` fixed (>= 0),
    off (-1: chunks carry ``n_action_steps``, nothing is bridged), or ``"auto"``, measured online.

    ``auto`` measures what policy_node can see: its observation's stamp to the chunk's
    publication, on the node's clock (the sim clock on simulated time), plus ``transport_s`` for
    what it cannot see (DDS delivery to franka_node and the control tick that applies the chunk).
    The estimate is the ``PERCENTILE`` (95) of the last ``WINDOW`` (20) measurements, taken as the
    nearest measurement (the largest while 11 or fewer are in, the second largest of 20: one
    outlier is ignored, two count at once), plus ``transport_s``: a high percentile because an
    underestimate leaves the arm standing at each boundary while an overestimate only publishes
    a step the next chunk replaces.
    Before the first measurement it is ``initial_s``, which the node sets to the most its chunks
    can bridge, for the same reason."""

    WINDOW = 20
    PERCENTILE = 95.0

    def __init__(self, latency_s, transport_s: float = DEFAULT_TRANSPORT_S, initial_s: float = 0.0):
        self.auto = latency_s == "auto"
        if not self.auto and (
            isinstance(latency_s, bool)
            or not isinstance(latency_s, (int, float))
            or not (latency_s == -1 or 0 <= latency_s < 10)
        ):
            raise ValueError(f"latency_s must be 'auto', -1 (off) or 0..10 s, got {latency_s!r}")
        if isinstance(transport_s, bool) or not (isinstance(transport_s, (int, float)) and 0 <= transport_s < 1):
            raise ValueError(f"the transport allowance must be within 0..1 s, got {transport_s!r}")
        self.fixed_s = None if self.auto else float(latency_s)
        self.transport_s = float(transport_s)
        self.initial_s = float(initial_s)
        self.measured: collections.deque[float] = collections.deque(maxlen=self.WINDOW)

    @property
    def off(self) -> bool:
        return self.fixed_s == -1

    def add(self, observation_to_publication_s: float) -> None:
        """One chunk's observation stamp -> publication, seconds on the node's clock."""
        if math.isfinite(observation_to_publication_s):
            self.measured.append(max(0.0, float(observation_to_publication_s)))

    @property
    def value_s(self) -> float | None:
        """L in seconds (None when off)."""
        if not self.auto:
            return None if self.off else self.fixed_s
        if not self.measured:
            return self.initial_s
        return float(np.percentile(self.measured, self.PERCENTILE, method="nearest")) + self.transport_s

    @property
    def source(self) -> str:
        """How ``value_s`` came about: fixed, off, auto (measured) or auto (initial)."""
        if not self.auto:
            return "off" if self.off else "fixed"
        return "auto" if self.measured else "auto (initial)"


class RealTimeChunking:
    """Real-time chunking for a DDIM policy by guided inpainting: each chunk's denoising is
    pulled towards the previous chunk where the two overlap in time.

    A chunk's step i runs at its observation's stamp + i·dt, so the previous chunk (all its
    predicted steps, absolute actions) is shifted by the periods between the two observations.
    The new chunk's first ``delay_steps`` steps fall due before it can arrive (the latency):
    they are the previous chunk's, exactly (weight 1). The rest of the overlap is guided with
    weights decaying from 1 to 0 (RTC's exponential schedule, Black et al. 2025), so the new
    chunk joins the running one and then follows its own observation. The guidance itself is
    ``models.sampling.ddim_sample``'s ``guide``; ``InferencePolicy.predict`` encodes the target
    relative to the current gripper state as the actions themselves are."""

    def __init__(self, delay_steps: int, dt_ns: int, max_gap_m: float, max_age_ns: int | None = None):
        """``max_gap_m``: a previous chunk whose step for the new observation's instant lies
        farther than this from the TCP observed then is not what the arm is executing (franka_node
        rejected it, or the arm was stopped); pinning the new chunk to it would repeat the
        rejection for ever (measured in the twin before this check: 13 of 13 chunks rejected).
        So it is franka_node's first-step jump limit (control.yaml ``safety.max_first_step_jump_m``),
        passed in by whoever runs the policy."""
        if delay_steps < 0:
            raise ValueError(f"delay_steps must be >= 0, got {delay_steps}")
        if not max_gap_m > 0:
            raise ValueError(f"max_gap_m must be positive, got {max_gap_m}")
        self.delay_steps = int(delay_steps)
        self.dt_ns = int(dt_ns)
        self.max_age_ns = max_age_ns  # a previous chunk older than this is forgotten (a pause, a new episode)
        self.max_gap_m = float(max_gap_m)
        self._previous: tuple[int, np.ndarray] | None = None  # (stamp, (H, 10) absolute actions)

    @staticmethod
    def delay_for(latency_s: float, dt_s: float) -> int:
        """Steps of a new chunk already due when it arrives ``latency_s`` after its observation
        (step 0, at the observation itself, always is)."""
        return math.floor(round(latency_s / dt_s, 6)) + 1

    def reset(self) -> None:
        self._previous = None

    def remember(self, stamp_ns: int, actions: np.ndarray) -> None:
        """The chunk just predicted for the observation at ``stamp_ns``: all its steps (H, 10)."""
        self._previous = (int(stamp_ns), np.array(actions, dtype=np.float64))

    def guide(self, stamp_ns: int, ee: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray] | None:
        """(target (H, 10) absolute actions, weights (H,)) for the observation at ``stamp_ns``
        with the TCP state ``ee`` (10-D action); None when there is no previous chunk overlapping
        it, or when that chunk is more than ``max_gap_m`` from ``ee`` (it was not executed)."""
        if self._previous is None:
            return None
        prev_stamp, prev = self._previous
        age = int(stamp_ns) - prev_stamp
        if age < 0 or (self.max_age_ns is not None and age > self.max_age_ns):
            return None
        horizon = len(prev)
        shift = round(age / self.dt_ns)
        overlap = horizon - shift  # new steps 0 .. overlap-1 are the previous chunk's shift ..
        if overlap <= 0:
            return None
        target = np.repeat(prev[-1:], horizon, axis=0)  # rows past the overlap get weight 0
        target[:overlap] = prev[shift:]
        if ee is not None and np.linalg.norm(target[0, :3] - np.asarray(ee)[:3]) > self.max_gap_m:
            self._previous = None
            return None
        weights = np.zeros(horizon)
        hard = min(self.delay_steps, overlap)
        weights[:hard] = 1.0
        soft = np.arange(hard, overlap)
        if len(soft):
            c = (overlap - soft) / (overlap - hard + 1)  # in (0, 1): 1 right after the hard part
            weights[hard:overlap] = c * np.expm1(c) / np.expm1(1.0)
        return target, weights


def validate_chunk(chunk: PoseChunk) -> None:
    times, poses, widths = (np.asarray(a) for a in (chunk.times_ns, chunk.poses, chunk.widths))
    if not isinstance(chunk.stamp_ns, (int, np.integer)) or isinstance(chunk.stamp_ns, bool):
        raise ChunkError(f"chunk stamp must be integer nanoseconds, got {chunk.stamp_ns!r}")
    if times.ndim != 1 or not np.issubdtype(times.dtype, np.integer):
        raise ChunkError(f"chunk step times must be a 1-D integer array, got {times.dtype} {times.shape}")
    k = len(times)
    if k == 0:
        raise ChunkError("chunk has no steps")
    if poses.shape != (k, 4, 4) or widths.shape != (k,):
        raise ChunkError(f"chunk arrays disagree: {k} times, poses {poses.shape}, widths {widths.shape}")
    if np.any(np.diff(times) < 0):
        raise ChunkError("chunk step times go backwards")
    if not np.issubdtype(widths.dtype, np.number) or not np.all(np.isfinite(widths)):
        raise ChunkError("chunk gripper widths contain NaN or inf", ChunkReason.NAN)
    if not np.issubdtype(poses.dtype, np.number) or not np.all(np.isfinite(poses)):
        raise ChunkError("chunk poses contain NaN or inf", ChunkReason.NAN)
    try:
        geometry.validate_pose(poses, tol=1e-3)
    except geometry.GeometryError as err:
        raise ChunkError(f"chunk pose invalid: {err}", ChunkReason.NAN) from err


def chunk_from_actions(actions: np.ndarray, stamp_ns: int, dt_ns: int, start_step: int = 0) -> PoseChunk:
    """Actions (K, 10) -> chunk with step i at ``stamp_ns + (start_step + i) * dt_ns``."""
    actions = np.asarray(actions, dtype=np.float64)
    try:
        poses, widths = geometry.action_to_pose(actions)
    except geometry.GeometryError as err:
        raise ChunkError(f"actions invalid: {err}", ChunkReason.NAN) from err
    times = stamp_ns + (start_step + np.arange(len(actions), dtype=np.int64)) * int(dt_ns)
    return PoseChunk(int(stamp_ns), times, poses, np.asarray(widths, dtype=np.float64))


def chunk_to_msg(chunk: PoseChunk, factory: MsgFactory, frame_id: str):
    """PoseChunk -> trajectory_msgs/MultiDOFJointTrajectory (rclpy or rosbags flavour)."""
    positions, quats = geometry.pos_quat_from_pose(chunk.poses)
    mk = factory.make
    identity = mk("geometry_msgs/msg/Quaternion", x=0.0, y=0.0, z=0.0, w=1.0)
    points = []
    for p, q, w, t in zip(positions, quats, chunk.widths, chunk.times_ns):
        tcp = mk(
            "geometry_msgs/msg/Transform",
            translation=mk("geometry_msgs/msg/Vector3", x=float(p[0]), y=float(p[1]), z=float(p[2])),
            rotation=mk("geometry_msgs/msg/Quaternion", x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])),
        )
        gripper = mk(
            "geometry_msgs/msg/Transform",
            translation=mk("geometry_msgs/msg/Vector3", x=float(w), y=0.0, z=0.0),
            rotation=identity,
        )
        points.append(
            mk(
                "trajectory_msgs/msg/MultiDOFJointTrajectoryPoint",
                transforms=[tcp, gripper],
                velocities=[],
                accelerations=[],
                time_from_start=factory.duration(int(t) - chunk.stamp_ns),
            )
        )
    return mk(
        "trajectory_msgs/msg/MultiDOFJointTrajectory",
        header=factory.header(chunk.stamp_ns, frame_id),
        joint_names=list(JOINT_NAMES),
        points=points,
    )


def chunk_from_msg(msg, frame_id: str | None = None) -> PoseChunk:
    """MultiDOFJointTrajectory (either flavour) -> validated PoseChunk; raises ChunkError.

    ``joint_names`` must be exactly ``JOINT_NAMES`` and every step must carry one transform per
    joint; with ``frame_id`` (the receiver's base frame) the header's frame must be it."""
    names = list(msg.joint_names)
    if names != list(JOINT_NAMES):
        raise ChunkError(f"chunk joint_names must be {list(JOINT_NAMES)}, got {names}")
    if frame_id is not None and str(msg.header.frame_id) != frame_id:
        raise ChunkError(f"chunk frame_id {str(msg.header.frame_id)!r} is not {frame_id!r}")
    if not msg.points:
        raise ChunkError("chunk has no steps")
    stamp = stamp_to_ns(msg.header.stamp)
    times, positions, quats, widths = [], [], [], []
    for i, point in enumerate(msg.points):
        if len(point.transforms) != len(names):
            raise ChunkError(f"step {i} has {len(point.transforms)} transforms for {len(names)} joints")
        tcp, gripper = point.transforms
        times.append(stamp + stamp_to_ns(point.time_from_start))
        positions.append([tcp.translation.x, tcp.translation.y, tcp.translation.z])
        quats.append([tcp.rotation.x, tcp.rotation.y, tcp.rotation.z, tcp.rotation.w])
        widths.append(gripper.translation.x)
    quats = np.asarray(quats, dtype=np.float64)
    if not np.all(np.isfinite(quats)) or not np.all(np.isfinite(positions)):
        raise ChunkError("chunk poses contain NaN or inf", ChunkReason.NAN)
    norms = np.linalg.norm(quats, axis=1)
    if np.any(np.abs(norms - 1.0) > 1e-3):
        raise ChunkError(f"chunk quaternions are not unit length (|q| = {norms.round(4).tolist()})", ChunkReason.NAN)
    poses = geometry.pose_from_pos_quat(np.asarray(positions), quats)
    return PoseChunk(stamp, np.asarray(times, dtype=np.int64), poses, np.asarray(widths, dtype=np.float64))
