"""Where the arm takes the board: TCP poses inside the workspace and the safety box where every camera sees all of it.

Visibility is judged with the *current* (hand-typed or previous) extrinsics and the board's
nominal mount, so rough guesses suffice: a camera sees a pose if every inner corner lands at
least ``margin_px`` inside its image, no more obliquely than ``max_view_angle_deg``, and no line
of sight passes through capsules standing in for the hand, wrist and forearm. A pose is kept if
``cameras_per_pose`` cameras see it. From many random candidates (position in the workspace
box where it overlaps lab.yaml's ``safety_box``, yaw about the vertical, tilt about a horizontal
axis, within control.yaml's orientation cone) a greedy farthest-point pick keeps
the most varied ``poses``, each time among the poses that the camera with the fewest views so
far can see, and orders them so that consecutive moves are short.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from ..config import LabConfig
from ..geometry import invert_pose
from .board import BoardSpec, CalibrationError
from .limits import MotionLimits
from .solve import CameraModel, project_points

# TCP pointing straight down, its x along the base's x (the FR3's usual grasping orientation).
R_DOWN = np.diag([1.0, -1.0, -1.0])


@dataclass(frozen=True)
class PlanConfig:
    poses: int = 20
    candidates: int = 3000
    max_yaw_deg: float = 45.0  # about the vertical, from R_DOWN
    max_tilt_deg: float = 20.0  # about a horizontal axis
    min_tcp_height: float = 0.15  # m above the table (base z); the board is above the TCP
    min_reach: float = 0.35  # m, TCP's horizontal distance from the base: closer, the FR3 folds up
    min_board_height: float = 0.03  # m: every board corner at least this high
    margin_px: float = 15.0
    max_view_angle_deg: float = 65.0
    # Cameras that must see the whole board from each pose (None: all). The hand and forearm hide
    # the board from a camera on the far side, so with three cameras around the table two per
    # pose is what the geometry allows; the pick then spreads poses so every camera sees many.
    cameras_per_pose: int | None = 2
    seed: int = 0


def arm_capsules(T_base_tcp: np.ndarray) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """(start, end, radius) of capsules that roughly enclose the FR3's hand, wrist and forearm.

    Only for planning (which board corners the arm would hide): the hand and wrist rise ~0.3 m
    along the TCP's -z; the forearm runs from there back towards the shoulder (~0.33 m above
    the base). Generous radii: a pose kept for nothing costs less than one without a view.
    """
    tcp, y, z = T_base_tcp[:3, 3], T_base_tcp[:3, 1], T_base_tcp[:3, 2]
    wrist = tcp - 0.30 * z
    shoulder = np.array([0.0, 0.0, 0.333])
    elbow = wrist + 0.5 * (shoulder - wrist) + np.array([0.0, 0.0, 0.15])
    hand = tcp - 0.08 * z  # the hand is ~0.2 m wide across the fingers (its y) and the fingers hang below
    return [
        (tcp - 0.02 * z, wrist, 0.07),
        (wrist, elbow, 0.07),
        (hand - 0.09 * y, hand + 0.09 * y, 0.045),
        (tcp - 0.03 * z - 0.05 * y, tcp - 0.03 * z + 0.05 * y, 0.035),
    ]


def _segment_distance(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    ab = b - a
    t = np.clip((points - a) @ ab / (ab @ ab), 0.0, 1.0)
    return np.linalg.norm(points - (a + t[..., None] * ab), axis=-1)


def board_visible(
    spec: BoardSpec,
    T_base_board: np.ndarray,
    T_base_cam: np.ndarray,
    cam: CameraModel,
    margin_px: float,
    max_view_angle_deg: float,
    occluders: list[tuple[np.ndarray, np.ndarray, float]] = (),
) -> bool:
    """Whether ``cam`` would see every inner corner: in its image with a margin, not edge-on,
    and (given ``occluders``, capsules in the base frame) with a free line of sight."""
    T = invert_pose(T_base_cam) @ T_base_board
    pts = spec.corners() @ T[:3, :3].T + T[:3, 3]
    if np.any(pts[:, 2] < 0.1):
        return False
    normal = T[:3, 2]
    sight = T[:3, 3] / np.linalg.norm(T[:3, 3])
    if normal @ sight < math.cos(math.radians(max_view_angle_deg)):
        return False  # seen edge-on, or from behind (the printed side faces -z)
    uv = project_points(cam.K, cam.dist, pts)
    if not (
        np.all(uv >= margin_px)
        and np.all(uv[:, 0] <= cam.width - 1 - margin_px)
        and np.all(uv[:, 1] <= cam.height - 1 - margin_px)
    ):
        return False
    if occluders:
        # points along each line of sight, stopping 1 cm short of the corner (the board's own mount)
        corners = spec.corners() @ T_base_board[:3, :3].T + T_base_board[:3, 3]
        eye = T_base_cam[:3, 3]
        along = np.linspace(0.0, 1.0, 40)[:, None, None]
        sight = corners - eye
        stop = 1.0 - 0.01 / np.linalg.norm(sight, axis=1)[None, :, None]
        samples = eye + along * stop * sight
        for a, b, radius in occluders:
            if np.any(_segment_distance(samples, a, b) < radius):
                return False
    return True


def plan_poses(
    lab: LabConfig,
    cameras: list[CameraModel],
    spec: BoardSpec,
    T_tcp_board: np.ndarray,
    cfg: PlanConfig = PlanConfig(),
    start: np.ndarray | None = None,
    limits: MotionLimits | None = None,
) -> list[np.ndarray]:
    """``cfg.poses`` TCP poses (4x4, base frame) that every camera should see the board from,
    inside ``limits`` (default: lab.yaml's safety box and the project's control.yaml) and checked
    against them."""
    limits = limits or MotionLimits.load(lab)
    rng = np.random.default_rng(cfg.seed)
    ws = lab.workspace
    lo = np.maximum(np.maximum(ws.lower, limits.lower), [-np.inf, -np.inf, cfg.min_tcp_height])
    hi = np.minimum(ws.upper, limits.upper)
    if np.any(hi <= lo):
        raise CalibrationError(
            f"the workspace {ws.lower}..{ws.upper} and the safety box {limits.lower}..{limits.upper} "
            f"have no room in common above min_tcp_height {cfg.min_tcp_height} m"
        )
    cone_deg = math.degrees(limits.max_tilt_rad)
    if cfg.max_tilt_deg > cone_deg:
        raise CalibrationError(
            f"a tilt of up to {cfg.max_tilt_deg:.0f} deg (--max-tilt) leaves franka_node's orientation cone "
            f"of {cone_deg:.0f} deg (control.yaml safety.max_tilt_rad): choose --max-tilt {cone_deg:.0f} or less"
        )
    guesses = {c.name: c.extrinsics.matrix() for c in lab.cameras}
    need = len(cameras) if cfg.cameras_per_pose is None else min(cfg.cameras_per_pose, len(cameras))
    accepted, features, seen_by = [], [], []
    for _ in range(cfg.candidates):
        p = rng.uniform(lo, hi)
        if math.hypot(p[0], p[1]) < cfg.min_reach:
            continue
        yaw = math.radians(rng.uniform(-cfg.max_yaw_deg, cfg.max_yaw_deg))
        axis_angle = rng.uniform(0, 2 * math.pi)
        tilt = math.radians(cfg.max_tilt_deg) * math.sqrt(rng.uniform())  # uniform over the tilt disc
        tilt_vec = tilt * np.array([math.cos(axis_angle), math.sin(axis_angle), 0.0])
        R = Rotation.from_rotvec(tilt_vec).as_matrix() @ Rotation.from_euler("z", yaw).as_matrix() @ R_DOWN
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, p
        board = T @ T_tcp_board
        if np.min((spec.corners() @ board[:3, :3].T + board[:3, 3])[:, 2]) < cfg.min_board_height:
            continue
        arm = arm_capsules(T)
        seen = np.array(
            [
                board_visible(spec, board, guesses[cam.name], cam, cfg.margin_px, cfg.max_view_angle_deg, arm)
                for cam in cameras
            ]
        )
        if seen.sum() >= need:
            accepted.append(T)
            seen_by.append(seen)
            # position in decimetres and rotation in radians weigh alike in "how different"
            features.append(np.concatenate([p / 0.1, Rotation.from_matrix(R @ R_DOWN.T).as_rotvec()]))
    seen_by = np.array(seen_by, dtype=bool).reshape(-1, len(cameras))
    short = [cam.name for c, cam in enumerate(cameras) if seen_by[:, c].sum() < cfg.poses // 2]
    if len(accepted) < cfg.poses or short:
        raise CalibrationError(
            f"only {len(accepted)} of {cfg.candidates} candidate poses show the whole board "
            f"to {need} cameras ({cfg.poses} wanted; too few for {short or 'all'}): check the "
            "cameras' current extrinsics and the board mount, or relax --max-tilt / margins"
        )
    features = np.array(features)
    chosen = [int(np.argmin(np.linalg.norm(features[:, :3] - (np.asarray(ws.center) / 0.1), axis=1)))]
    dist = np.linalg.norm(features - features[chosen[0]], axis=1)
    views = seen_by[chosen[0]].astype(int)
    while len(chosen) < cfg.poses:
        # the most different pose among those the least-served camera sees: every camera gets its share
        serves = seen_by[:, int(np.argmin(views))]
        k = int(np.argmax(np.where(serves, dist, -1.0)))
        chosen.append(k)
        views += seen_by[k]
        dist = np.minimum(dist, np.linalg.norm(features - features[k], axis=1))
    # nearest-neighbour tour from the start (or the first pick): short moves between captures
    here = (
        features[chosen[0]]
        if start is None
        else np.concatenate([start[:3, 3] / 0.1, Rotation.from_matrix(start[:3, :3] @ R_DOWN.T).as_rotvec()])
    )
    order, left = [], list(chosen)
    while left:
        k = min(left, key=lambda j: np.linalg.norm(features[j] - here))
        order.append(k)
        left.remove(k)
        here = features[k]
    poses = [accepted[k] for k in order]
    limits.check(poses)  # the sampling above keeps them inside; this guards that promise
    return poses
