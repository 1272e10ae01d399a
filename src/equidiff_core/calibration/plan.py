"""Where the arm takes the board: TCP poses inside the workspace where every camera sees all of it.

Visibility is judged with the *current* (hand-typed or previous) extrinsics and the board's
nominal mount, so rough guesses suffice: a pose is kept only if each camera would see every
inner corner at least ``margin_px`` inside its image and no more obliquely than
``max_view_angle_deg``. From many random candidates (position in the workspace box, yaw about
the vertical, tilt about a horizontal axis) a greedy farthest-point pick keeps the most
varied ``poses``, ordered so that consecutive moves are short.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from ..config import LabConfig
from .board import BoardSpec, CalibrationError
from .solve import CameraModel, inverse_pose, project_points

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
    seed: int = 0


def board_visible(spec: BoardSpec, T_base_board: np.ndarray, T_base_cam: np.ndarray, cam: CameraModel,
                  margin_px: float, max_view_angle_deg: float) -> bool:
    T = inverse_pose(T_base_cam) @ T_base_board
    pts = spec.corners() @ T[:3, :3].T + T[:3, 3]
    if np.any(pts[:, 2] < 0.1):
        return False
    normal = T[:3, 2]
    sight = T[:3, 3] / np.linalg.norm(T[:3, 3])
    if normal @ sight < math.cos(math.radians(max_view_angle_deg)):
        return False  # seen edge-on, or from behind (the printed side faces -z)
    uv = project_points(cam.K, cam.dist, pts)
    return bool(np.all(uv >= margin_px) and np.all(uv[:, 0] <= cam.width - 1 - margin_px)
                and np.all(uv[:, 1] <= cam.height - 1 - margin_px))


def plan_poses(lab: LabConfig, cameras: list[CameraModel], spec: BoardSpec, T_tcp_board: np.ndarray,
               cfg: PlanConfig = PlanConfig(), start: np.ndarray | None = None) -> list[np.ndarray]:
    """``cfg.poses`` TCP poses (4x4, base frame) that every camera should see the board from."""
    rng = np.random.default_rng(cfg.seed)
    ws = lab.workspace
    lo = np.maximum(ws.lower, [-np.inf, -np.inf, cfg.min_tcp_height])
    hi = ws.upper
    if np.any(hi <= lo):
        raise CalibrationError(f"the workspace {ws.lower}..{ws.upper} has no room above "
                               f"min_tcp_height {cfg.min_tcp_height} m")
    guesses = {c.name: c.extrinsics.matrix() for c in lab.cameras}
    accepted, features = [], []
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
        if all(board_visible(spec, board, guesses[cam.name], cam, cfg.margin_px, cfg.max_view_angle_deg)
               for cam in cameras):
            accepted.append(T)
            # position in decimetres and rotation in radians weigh alike in "how different"
            features.append(np.concatenate([p / 0.1, Rotation.from_matrix(R @ R_DOWN.T).as_rotvec()]))
    if len(accepted) < cfg.poses:
        raise CalibrationError(f"only {len(accepted)} of {cfg.candidates} candidate poses let every camera "
                               f"see the whole board ({cfg.poses} wanted): check the cameras' current "
                               "extrinsics and the board mount, or relax --max-tilt / margins")
    features = np.array(features)
    chosen = [int(np.argmin(np.linalg.norm(features[:, :3] - (np.asarray(ws.center) / 0.1), axis=1)))]
    dist = np.linalg.norm(features - features[chosen[0]], axis=1)
    while len(chosen) < cfg.poses:
        k = int(np.argmax(dist))
        chosen.append(k)
        dist = np.minimum(dist, np.linalg.norm(features - features[k], axis=1))
    # nearest-neighbour tour from the start (or the first pick): short moves between captures
    here = features[chosen[0]] if start is None else np.concatenate(
        [start[:3, 3] / 0.1, Rotation.from_matrix(start[:3, :3] @ R_DOWN.T).as_rotvec()])
    order, left = [], list(chosen)
    while left:
        k = min(left, key=lambda j: np.linalg.norm(features[j] - here))
        order.append(k)
        left.remove(k)
        here = features[k]
    return [accepted[k] for k in order]
