"""Eye-to-hand calibration: each fixed camera's T_base_optical from a board carried by the arm.

Unknowns: ``T_base_cam`` per camera (X) and one ``T_tcp_board`` (Y, where the board sits on
the hand). Every sample i gives the TCP pose ``H_i`` (robot) and, per camera that saw the
board, its pose ``C_i = T_cam_board`` (PnP), with X C_i = H_i Y.

1. ``solve_hand_eye``: closed-form per camera (Park & Martin 1994). Between samples i and j,
   A X = X B with A = H_j H_i^-1 and B = C_j C_i^-1; the rotation follows from the motions'
   rotation axes (Kabsch), the translation from linear least squares. OpenCV's
   ``calibrateHandEye`` would do this step, but the Python bindings of opencv-contrib 5.0.0.93
   export only its CALIB_HAND_EYE_* constants, not the function (checked), so we keep the
   ~30 lines here; test_hand_eye_opencv.py checks them against OpenCV 4.x's solvers.
2. ``refine``: all cameras and the one board-in-hand transform together, minimising the
   corners' reprojection error in pixels over every detection (scipy ``least_squares``,
   soft-L1 loss so a bad detection cannot drag the result).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from ..geometry import invert_pose, make_pose, rotation_angle
from .board import BoardSpec, CalibrationError, Detection, board_pose


@dataclass(frozen=True)
class CameraModel:
    """A camera's colour intrinsics in OpenCV's convention (pixel centres at integers)."""

    name: str
    K: np.ndarray  # 3x3
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))
    width: int = 0
    height: int = 0


@dataclass
class Sample:
    """One robot pose: the measured TCP and the board as each camera saw it (absent = not seen)."""

    T_base_tcp: np.ndarray
    detections: dict[str, Detection]


def pose_error(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """(translation error mm, rotation error deg) between two poses."""
    return (
        float(np.linalg.norm(T_est[:3, 3] - T_true[:3, 3]) * 1000),
        math.degrees(rotation_angle(T_est[:3, :3], T_true[:3, :3])),
    )


def mean_pose(poses: list[np.ndarray]) -> np.ndarray:
    R = Rotation.from_matrix(np.stack([T[:3, :3] for T in poses])).mean().as_matrix()
    return make_pose(R, np.mean([T[:3, 3] for T in poses], axis=0))


def solve_hand_eye(
    T_base_tcp: list[np.ndarray], T_cam_board: list[np.ndarray], min_angle_deg: float = 5.0
) -> tuple[np.ndarray, np.ndarray]:
    """Closed-form eye-to-hand: (T_base_cam, T_tcp_board) from paired robot and board poses."""
    n = len(T_base_tcp)
    if n != len(T_cam_board) or n < 3:
        raise CalibrationError(f"hand-eye needs at least 3 paired poses, got {n}")
    alphas, betas, pairs = [], [], []
    for i in range(n):
        for j in range(i + 1, n):
            A = T_base_tcp[j] @ invert_pose(T_base_tcp[i])
            B = T_cam_board[j] @ invert_pose(T_cam_board[i])
            a = Rotation.from_matrix(A[:3, :3]).as_rotvec()
            b = Rotation.from_matrix(B[:3, :3]).as_rotvec()
            if np.linalg.norm(a) < math.radians(min_angle_deg):
                continue  # near-pure translations say nothing about the rotation and amplify noise
            alphas.append(a)
            betas.append(b)
            pairs.append((A, B))
    if len(pairs) < 2:
        raise CalibrationError(
            "the poses rotate the board too little: turn the hand by "
            f"more than {min_angle_deg:.0f} deg about at least two different axes"
        )
    alphas, betas = np.array(alphas), np.array(betas)
    axes = alphas / np.linalg.norm(alphas, axis=1, keepdims=True)
    if np.linalg.svd(axes, compute_uv=False)[1] < 0.1:
        raise CalibrationError(
            "every pose change rotates about (nearly) the same axis: the camera "
            "pose is not determined; add tilts about another axis"
        )
    # Kabsch: R_X = argmin sum |alpha - R beta|^2
    U, _, Vt = np.linalg.svd(alphas.T @ betas)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R_X = U @ D @ Vt
    lhs = np.vstack([A[:3, :3] - np.eye(3) for A, _ in pairs])
    rhs = np.concatenate([R_X @ B[:3, 3] - A[:3, 3] for A, B in pairs])
    t_X = np.linalg.lstsq(lhs, rhs, rcond=None)[0]
    X = make_pose(R_X, t_X)
    Y = mean_pose([invert_pose(H) @ X @ C for H, C in zip(T_base_tcp, T_cam_board)])
    return X, Y


@dataclass
class CameraResult:
    name: str
    T_base_cam: np.ndarray
    detections: int  # samples in which this camera saw the board
    corners: int  # corner observations used
    rms_px: float  # corner reprojection RMS after the joint refinement
    max_px: float
    # the same residuals as distances on the board (pixel error x depth / focal length)
    rms_mm: float
    max_mm: float
    hand_eye_T_base_cam: np.ndarray  # the closed-form solution before refinement

    def summary(self) -> dict:
        return {
            "detections": self.detections,
            "corners": self.corners,
            "rms_px": round(self.rms_px, 3),
            "max_px": round(self.max_px, 3),
            "rms_mm": round(self.rms_mm, 3),
            "max_mm": round(self.max_mm, 3),
        }


@dataclass
class Calibration:
    cameras: dict[str, CameraResult]
    T_tcp_board: np.ndarray
    samples: int
    optimizer_cost: float


def project_points(K: np.ndarray, dist: np.ndarray, pts_cam: np.ndarray) -> np.ndarray:
    import cv2

    uv, _ = cv2.projectPoints(pts_cam.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, dist)
    return uv.reshape(-1, 2)


def calibrate(
    spec: BoardSpec, cameras: list[CameraModel], samples: list[Sample], min_detections: int = 4
) -> Calibration:
    """Hand-eye per camera, then the joint reprojection refinement over all cameras."""
    corners = spec.corners()
    pnp: dict[str, list[tuple[int, np.ndarray]]] = {}
    for cam in cameras:
        seen = [
            (i, board_pose(spec, s.detections[cam.name], cam.K, cam.dist)[0])
            for i, s in enumerate(samples)
            if cam.name in s.detections
        ]
        if len(seen) < min_detections:
            raise CalibrationError(
                f"camera {cam.name} saw the board in {len(seen)} of {len(samples)} poses; "
                f"at least {min_detections} are needed (is it pointed at the workspace? "
                "is the board in its view?)"
            )
        pnp[cam.name] = seen
    hand_eye = {}
    boards = []
    for cam in cameras:
        idx = [i for i, _ in pnp[cam.name]]
        X, Y = solve_hand_eye([samples[i].T_base_tcp for i in idx], [C for _, C in pnp[cam.name]])
        hand_eye[cam.name] = X
        boards.append(Y)
    Y0 = mean_pose(boards)

    # Parameters: small corrections (rotation vector, translation) to Y0 and to each X0.
    obs = [(c, i, samples[i].detections[cam.name]) for c, cam in enumerate(cameras) for i, _ in pnp[cam.name]]

    def unpack(x: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
        def delta(v):
            return make_pose(Rotation.from_rotvec(v[:3]).as_matrix(), v[3:6])

        Y = Y0 @ delta(x[:6])
        Xs = [hand_eye[cam.name] @ delta(x[6 + 6 * c : 12 + 6 * c]) for c, cam in enumerate(cameras)]
        return Y, Xs

    def residuals(x: np.ndarray) -> np.ndarray:
        Y, Xs = unpack(x)
        inv_X = [invert_pose(X) for X in Xs]
        out = []
        for c, i, det in obs:
            T = inv_X[c] @ samples[i].T_base_tcp @ Y
            pts = corners[det.ids] @ T[:3, :3].T + T[:3, 3]
            out.append((project_points(cameras[c].K, cameras[c].dist, pts) - det.pixels).ravel())
        return np.concatenate(out)

    x0 = np.zeros(6 + 6 * len(cameras))
    # x_scale: radians and metres move pixels alike at ~1 m range; soft-L1 at 1 px
    sol = least_squares(residuals, x0, loss="soft_l1", f_scale=1.0, x_scale=0.01, method="trf")
    Y, Xs = unpack(sol.x)
    results = {}
    for c, cam in enumerate(cameras):
        inv_X = invert_pose(Xs[c])
        px, mm = [], []
        for cc, i, det in obs:
            if cc != c:
                continue
            T = inv_X @ samples[i].T_base_tcp @ Y
            pts = corners[det.ids] @ T[:3, :3].T + T[:3, 3]
            e = np.linalg.norm(project_points(cam.K, cam.dist, pts) - det.pixels, axis=1)
            px.append(e)
            mm.append(e * pts[:, 2] / cam.K[0, 0] * 1000)  # the pixel error as a distance at the corner's depth
        px, mm = np.concatenate(px), np.concatenate(mm)
        results[cam.name] = CameraResult(
            cam.name,
            Xs[c],
            len(pnp[cam.name]),
            len(px),
            float(np.sqrt(np.mean(px**2))),
            float(px.max()),
            float(np.sqrt(np.mean(mm**2))),
            float(mm.max()),
            hand_eye[cam.name],
        )
    return Calibration(results, Y, len(samples), float(sol.cost))
