"""SE(3) poses, the 10-D absolute action, and the SO(2) group actions EquiDiff relies on.

Conventions (shared with the official EquiDiff code and every other module here):

* A pose is a 4x4 homogeneous matrix in the robot base frame; batched as (..., 4, 4).
* The 10-D absolute action is ``[x, y, z, r6(6), width]`` where ``r6`` holds the first two
  *rows* of R (``R[0, :], R[1, :]``) and decoding re-orthonormalises them (Gram-Schmidt).
  Written as pairs ``(R[0, j], R[1, j])`` these are the xy components of R's columns, so a
  rotation g about the world z axis acts as rho1 on (x, y) and on each of the three pairs,
  and trivially on z and width: the paper's rho1^3 + (rho1 + rho0) + rho0.
* Rotations about z act about a workspace centre ``c``: p -> Rz (p - c) + c.
* Quaternions are scipy's scalar-last ``[x, y, z, w]``.

Every function takes numpy arrays or torch tensors and returns the same kind; leading
dimensions are batch dimensions. Invalid input (NaN, wrong shape, non-orthonormal
rotation) raises ``GeometryError``; nothing is silently repaired except by
``matrix_from_rot6d``, whose job is exactly that.
"""

from __future__ import annotations

import contextlib
import math
import sys
from contextvars import ContextVar
from typing import Any

import numpy as np


class _LazyTorch:
    """torch, imported on first use: a tensor argument means the caller has imported it already,
    and ROS nodes that only need numpy geometry start seconds sooner without importing it."""

    def __getattr__(self, name: str) -> Any:
        import torch

        return getattr(torch, name)


torch = _LazyTorch()

Array = Any  # np.ndarray | torch.Tensor

ACTION_DIM = 10
POS = slice(0, 3)
ROT6D = slice(3, 9)
WIDTH = 9
# Indices of the three (R[0, j], R[1, j]) pairs inside the action vector: each is a rho1 vector.
ROT6D_PAIRS = ((3, 6), (4, 7), (5, 8))
ORTHONORMAL_TOL = 1e-4


class GeometryError(ValueError):
    """Input that is not a valid pose, rotation or action."""


def _is_torch(x: Array) -> bool:
    loaded = sys.modules.get("torch")  # no tensor can exist before torch is imported
    return loaded is not None and isinstance(x, loaded.Tensor)


def _xp(x: Array):
    return torch if _is_torch(x) else np


def _asarray(x: Array) -> Array:
    return x if _is_torch(x) else np.asarray(x, dtype=np.float64)


def _check_finite(x: Array, what: str) -> None:
    finite = torch.isfinite(x).all().item() if _is_torch(x) else np.isfinite(x).all()
    if not finite:
        raise GeometryError(f"{what} contains NaN or inf")


def _check_shape(x: Array, tail: tuple[int, ...], what: str) -> None:
    if tuple(x.shape[-len(tail) :]) != tail or x.ndim < len(tail):
        raise GeometryError(f"{what} must have shape (..., {', '.join(map(str, tail))}), got {tuple(x.shape)}")


def validate_rotation(R: Array, tol: float = ORTHONORMAL_TOL) -> Array:
    """Return ``R`` if it is a finite, orthonormal, right-handed (..., 3, 3) matrix; raise otherwise."""
    R = _asarray(R)
    _check_shape(R, (3, 3), "rotation")
    _check_finite(R, "rotation")
    xp = _xp(R)
    eye = xp.eye(3, dtype=R.dtype) if xp is np else torch.eye(3, dtype=R.dtype, device=R.device)
    size = R.numel() if _is_torch(R) else R.size
    err = xp.abs(R @ R.swapaxes(-1, -2) - eye).max() if size else 0.0
    if float(err) > tol:
        raise GeometryError(f"rotation is not orthonormal (max |R R^T - I| = {float(err):.3g} > {tol})")
    det = xp.linalg.det(R)
    if bool((det < 0).any()):
        raise GeometryError("rotation has determinant -1 (a reflection, not a rotation)")
    return R


def validate_pose(T: Array, tol: float = ORTHONORMAL_TOL) -> Array:
    """Return ``T`` if it is a finite homogeneous (..., 4, 4) pose with a proper rotation."""
    T = _asarray(T)
    _check_shape(T, (4, 4), "pose")
    _check_finite(T, "pose")
    validate_rotation(T[..., :3, :3], tol)
    xp = _xp(T)
    bottom = T[..., 3, :]
    expected = xp.zeros_like(bottom)
    expected[..., 3] = 1
    if float(xp.abs(bottom - expected).max()) > tol:
        raise GeometryError("pose's last row must be [0, 0, 0, 1]")
    return T


def rot6d_from_matrix(R: Array) -> Array:
    """(..., 3, 3) -> (..., 6): the first two rows of R, as the official EquiDiff code does."""
    R = _asarray(R)
    _check_shape(R, (3, 3), "rotation")
    return R[..., :2, :].reshape(*R.shape[:-2], 6)


def matrix_from_rot6d(d6: Array, eps: float = 1e-8) -> Array:
    """(..., 6) -> (..., 3, 3): Gram-Schmidt on the two rows; raises on NaN or degenerate input."""
    d6 = _asarray(d6)
    _check_shape(d6, (6,), "rot6d")
    _check_finite(d6, "rot6d")
    xp = _xp(d6)
    a1, a2 = d6[..., :3], d6[..., 3:]
    n1 = xp.linalg.norm(a1, axis=-1, keepdims=True) if xp is np else torch.linalg.norm(a1, dim=-1, keepdim=True)
    if float(n1.min()) < eps:
        raise GeometryError("rot6d's first row has zero length")
    b1 = a1 / n1
    a2 = a2 - (b1 * a2).sum(-1, keepdims=True) * b1 if xp is np else a2 - (b1 * a2).sum(-1, keepdim=True) * b1
    n2 = xp.linalg.norm(a2, axis=-1, keepdims=True) if xp is np else torch.linalg.norm(a2, dim=-1, keepdim=True)
    if float(n2.min()) < eps:
        raise GeometryError("rot6d's rows are parallel")
    b2 = a2 / n2
    b3 = np.cross(b1, b2) if xp is np else torch.linalg.cross(b1, b2, dim=-1)
    return xp.stack([b1, b2, b3], -2) if xp is np else torch.stack([b1, b2, b3], dim=-2)


def make_pose(R: Array, p: Array) -> Array:
    """Assemble (..., 4, 4) poses from rotations (..., 3, 3) and positions (..., 3)."""
    R, p = _asarray(R), _asarray(p)
    xp = _xp(R)
    T = (
        xp.zeros((*R.shape[:-2], 4, 4), dtype=R.dtype)
        if xp is np
        else torch.zeros((*R.shape[:-2], 4, 4), dtype=R.dtype, device=R.device)
    )
    T[..., :3, :3] = R
    T[..., :3, 3] = p
    T[..., 3, 3] = 1
    return T


def invert_pose(T: np.ndarray) -> np.ndarray:
    """The inverse of a rigid transform (4, 4), exactly (transpose, not a general matrix inverse)."""
    R, p = T[:3, :3], T[:3, 3]
    return make_pose(R.T, -R.T @ p)


def rotation_angle(Ra: np.ndarray, Rb: np.ndarray) -> float:
    """Angle (rad) of the rotation taking Ra to Rb.

    atan2 of sine and cosine, not arccos of the cosine alone: arccos loses half the digits
    near 0 (1e-8 rad of noise at a true 0), where calibration errors and jump checks live."""
    R = np.asarray(Ra).T @ np.asarray(Rb)
    sin = np.linalg.norm([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / 2.0
    return float(np.arctan2(sin, (np.trace(R) - 1.0) / 2.0))


TOOL_DOWN = np.array([0.0, 0.0, -1.0])  # the tool axis (TCP z) of a gripper pointing straight down


def down_pose(position) -> np.ndarray:
    """The pose at ``position`` with the tool pointing straight down (the home orientation, no yaw)."""
    return make_pose(np.diag([1.0, -1.0, -1.0]), np.asarray(position, dtype=np.float64))


def tilt_angle(R: np.ndarray) -> float:
    """Angle (rad) between the tool axis of rotation ``R`` (its z column) and straight down.

    Not ``rotation_angle`` to a down pose: that counts yaw too, which the policy uses freely;
    the tilt is the swing part alone. atan2 as there (exact near 0)."""
    z = np.asarray(R, dtype=np.float64)[:3, 2]
    return float(np.arctan2(np.linalg.norm(np.cross(z, TOOL_DOWN)), float(z @ TOOL_DOWN)))


def limit_tilt(R: np.ndarray, max_tilt: float) -> np.ndarray:
    """``R`` swung back (about the axis of its tilt, yaw kept) so its tool axis is at most
    ``max_tilt`` from straight down; ``R`` itself when it already is."""
    from scipy.spatial.transform import Rotation

    R = np.asarray(R, dtype=np.float64)
    tilt = tilt_angle(R)
    if tilt <= max_tilt:
        return R
    axis = np.cross(R[:3, 2], TOOL_DOWN)
    n = float(np.linalg.norm(axis))
    axis = axis / n if n > 1e-9 else np.array([1.0, 0.0, 0.0])  # pointing straight up: any horizontal axis
    return Rotation.from_rotvec(axis * (tilt - max_tilt)).as_matrix() @ R


def pose_to_action(T: Array, width: Array) -> Array:
    """Poses (..., 4, 4) and gripper widths (...) -> absolute actions (..., 10)."""
    T = validate_pose(T)
    width = _asarray(width)
    if width.shape != T.shape[:-2]:
        raise GeometryError(f"width shape {tuple(width.shape)} does not match poses {tuple(T.shape[:-2])}")
    _check_finite(width, "gripper width")
    parts = [T[..., :3, 3], rot6d_from_matrix(T[..., :3, :3]), width[..., None]]
    return np.concatenate(parts, -1) if not _is_torch(T) else torch.cat(parts, dim=-1)


def action_to_pose(action: Array) -> tuple[Array, Array]:
    """Absolute actions (..., 10) -> (poses (..., 4, 4), widths (...))."""
    action = _asarray(action)
    _check_shape(action, (ACTION_DIM,), "action")
    _check_finite(action, "action")
    R = matrix_from_rot6d(action[..., ROT6D])
    return make_pose(R, action[..., POS]), action[..., WIDTH]


def pose_from_pos_quat(p: Array, q_xyzw: Array) -> np.ndarray:
    """Position (..., 3) and scalar-last quaternion (..., 4) -> pose (..., 4, 4) (numpy)."""
    p, q = np.asarray(p, dtype=np.float64), np.asarray(q_xyzw, dtype=np.float64)
    _check_finite(q, "quaternion")
    norm = np.linalg.norm(q, axis=-1)
    if np.any(np.abs(norm - 1.0) > 1e-3):
        raise GeometryError(f"quaternion is not unit length (|q| = {norm})")
    # scipy imported where used, here and below: `equidiff lab` commands never convert a quaternion, and it was
    # the largest of their imports
    from scipy.spatial.transform import Rotation

    R = Rotation.from_quat(q.reshape(-1, 4)).as_matrix().reshape(*q.shape[:-1], 3, 3)
    return make_pose(R, p)


def pos_quat_from_pose(T: Array) -> tuple[np.ndarray, np.ndarray]:
    """Pose (..., 4, 4) -> (position (..., 3), scalar-last quaternion (..., 4)) (numpy)."""
    from scipy.spatial.transform import Rotation

    T = validate_pose(np.asarray(T, dtype=np.float64))
    q = Rotation.from_matrix(T[..., :3, :3].reshape(-1, 3, 3)).as_quat().reshape(*T.shape[:-2], 4)
    return T[..., :3, 3].copy(), q


# --- SO(2) about the workspace z axis -------------------------------------------------------


def rho1(theta: float) -> np.ndarray:
    c, s = math.cos(theta), math.sin(theta)
    return np.array([[c, -s], [s, c]])


def rotz(theta: float) -> np.ndarray:
    """3x3 rotation by ``theta`` about z."""
    R = np.eye(3)
    R[:2, :2] = rho1(theta)
    return R


def rotz_pose(theta: float, center: Array = (0.0, 0.0, 0.0)) -> np.ndarray:
    """4x4 transform T_g: rotation by ``theta`` about the vertical axis through ``center``."""
    center = np.asarray(center, dtype=np.float64)
    R = rotz(theta)
    return make_pose(R, center - R @ center)


def action_rep(theta: float) -> np.ndarray:
    """10x10 matrix of g acting linearly on an action with positions taken relative to the centre."""
    rep = np.eye(ACTION_DIM)
    r = rho1(theta)
    for i, j in ((0, 1), *ROT6D_PAIRS):
        rep[np.ix_([i, j], [i, j])] = r
    return rep


def _like(ref: Array, m: np.ndarray) -> Array:
    return torch.as_tensor(m, dtype=ref.dtype, device=ref.device) if _is_torch(ref) else m.astype(ref.dtype)


def rotate_action(action: Array, theta: float, center: Array = (0.0, 0.0, 0.0)) -> Array:
    """g . a for absolute actions (..., 10): rotate positions about ``center`` and orientations about z."""
    action = _asarray(action)
    _check_shape(action, (ACTION_DIM,), "action")
    offset = np.zeros(ACTION_DIM)
    offset[POS] = np.asarray(center, dtype=np.float64)
    offset = _like(action, offset)
    rep = _like(action, action_rep(theta))
    return (action - offset) @ rep.T + offset


def rotate_pose(T: Array, theta: float, center: Array = (0.0, 0.0, 0.0)) -> Array:
    """g . T = T_g T for poses (..., 4, 4)."""
    T = _asarray(T)
    _check_shape(T, (4, 4), "pose")
    return _like(T, rotz_pose(theta, center)) @ T


# --- Relative (delta) control: g . A = T_g A T_g^-1, paper appendices B and C --------------


def relative_rotation_rep(theta: float) -> np.ndarray:
    """9x9 rho_R with rho_R(g) vec_r(R) = vec_r(R_g R R_g^-1) (row-major flattening)."""
    Rg = rotz(theta)
    # vec_r(A X B) = (A kron B^T) vec_r(X)
    return np.kron(Rg, Rg)


def relative_pose_rep(theta: float) -> np.ndarray:
    """16x16 rho_A with rho_A(g) vec_r(A) = vec_r(T_g A T_g^-1) (T_g about the origin)."""
    Tg = rotz_pose(theta)
    return np.kron(Tg, Tg)


# Change of basis for the 9-D rotation part (paper appendix C): P rho_R P^-1 = rho0^3 + rho1^2 + rho2.
P_REL_ROT = np.array(
    [
        [1, 0, 0, 0, 1, 0, 0, 0, 0],
        [0, -1, 0, 1, 0, 0, 0, 0, 0],
        [0, 0, 0, 0, 0, 0, 0, 0, 1],
        [0, 0, 1, 0, 0, 0, 0, 0, 0],
        [0, 0, 0, 0, 0, 1, 0, 0, 0],
        [0, 0, 0, 0, 0, 0, 1, 0, 0],
        [0, 0, 0, 0, 0, 0, 0, 1, 0],
        [0, 1, 0, 1, 0, 0, 0, 0, 0],
        [-1, 0, 0, 0, 1, 0, 0, 0, 0],
    ],
    dtype=np.float64,
)
REL_ROT_IRREPS = (0, 0, 0, 1, 1, 2)  # frequencies of the blocks of P rho_R P^-1, in order

# Change of basis for the full 16-D relative pose (paper appendix B): rho0^6 + rho1^4 + rho2.
P_REL_POSE = np.zeros((16, 16))
for _row, _cols in enumerate(
    [
        {0: 1, 5: 1},
        {1: 1, 4: -1},
        {10: 1},
        {11: 1},
        {14: 1},
        {15: 1},
        {2: 1},
        {6: 1},
        {3: 1},
        {7: 1},
        {8: 1},
        {9: 1},
        {12: 1},
        {13: 1},
        {1: 1, 4: 1},
        {0: -1, 5: 1},
    ]
):
    for _col, _val in _cols.items():
        P_REL_POSE[_row, _col] = _val
REL_POSE_IRREPS = (0, 0, 0, 0, 0, 0, 1, 1, 1, 1, 2)


def irrep_block_diag(theta: float, frequencies: tuple[int, ...]) -> np.ndarray:
    """Block-diagonal matrix of SO(2) irreps rho_k(theta) (rho_0 = 1, rho_k = rho1(k theta))."""
    size = sum(1 if k == 0 else 2 for k in frequencies)
    out = np.zeros((size, size))
    i = 0
    for k in frequencies:
        if k == 0:
            out[i, i] = 1.0
            i += 1
        else:
            out[i : i + 2, i : i + 2] = rho1(k * theta)
            i += 2
    return out


def rotate_relative_pose(A: Array, theta: float) -> Array:
    """g . A = T_g A T_g^-1 for relative (delta) poses (..., 4, 4)."""
    A = _asarray(A)
    _check_shape(A, (4, 4), "relative pose")
    Tg = _like(A, rotz_pose(theta))
    Tg_inv = _like(A, rotz_pose(-theta))
    return Tg @ A @ Tg_inv


# --- Voxel grids ---------------------------------------------------------------------------


def rotate_voxel_grid(grid: Array, theta: float, mode: str = "nearest") -> Array:
    """Rotate (..., C, X, Y, Z) grids by ``theta`` about the z axis through the grid centre.

    Axis order is (x, y, z) of the base frame, index 0 at the workspace minimum (see
    voxels.py), so this matches ``rotate_action`` about the workspace centre: the content at
    a point and the pose at that point move together. Multiples of 90 deg are exact
    (``rot90`` with x -> y, counter-clockwise seen from above); other angles resample with
    ``mode`` 'nearest' or 'trilinear' (empty outside the rotated support).
    """
    quarter = theta / (math.pi / 2)
    k = round(quarter)
    if abs(quarter - k) < 1e-9:
        if _is_torch(grid):
            return torch.rot90(grid, k % 4, dims=(-3, -2))
        return np.rot90(np.asarray(grid), k % 4, axes=(-3, -2)).copy()
    if mode not in ("nearest", "trilinear"):
        raise GeometryError(f"unknown resampling mode {mode!r} (use 'nearest' or 'trilinear')")
    return _resample_rotated(grid, theta, mode)


# nearest rotation by resampling every x-y slice, as before _gather_columns (a context variable: scoped, thread-safe)
_SLICE_RESAMPLING: ContextVar[bool] = ContextVar("slice_resampling", default=False)


@contextlib.contextmanager
def slice_resampled_rotation():
    """Nearest rotations inside resample every x-y slice in float, as they did before they gathered whole
    columns: the same voxels at the old cost, for the benches (``equidiff bench train --variants
    slice_rotation``) and as the tests' reference."""
    token = _SLICE_RESAMPLING.set(True)
    try:
        yield
    finally:
        _SLICE_RESAMPLING.reset(token)


def _resample_rotated(grid: Array, theta: float, mode: str) -> Array:
    import torch.nn.functional as F

    is_t = _is_torch(grid)
    t = grid if is_t else torch.as_tensor(np.asarray(grid))
    *lead, C, X, Y, Z = t.shape
    if X != Y:
        raise GeometryError(f"rotation needs a square x-y grid, got {X}x{Y}")
    # affine_grid maps output coords to input coords in (W=Y-index, H=X-index) order.
    # Output point q comes from input R^-1 q. In (x=H, y=W) order R^-1 = [[c, s], [-s, c]];
    # in (W, H) order it becomes [[c, -s], [s, c]].
    c, s = math.cos(theta), math.sin(theta)
    affine = torch.tensor([[[c, -s, 0.0], [s, c, 0.0]]], dtype=torch.float32, device=t.device)
    if mode == "nearest" and not _SLICE_RESAMPLING.get():
        out = _gather_columns(t, _nearest_columns(affine, X, Y))
        return out if is_t else out.numpy()
    # Fold z into channels and resample each x-y slice: the rotation leaves z alone.
    img = t.reshape(-1, C, X, Y, Z).permute(0, 1, 4, 2, 3).reshape(-1, C * Z, X, Y).float()
    coords = F.affine_grid(affine.expand(img.shape[0], 2, 3), list(img.shape), align_corners=False)
    out = F.grid_sample(
        img, coords, mode="nearest" if mode == "nearest" else "bilinear", padding_mode="zeros", align_corners=False
    )
    out = out.reshape(-1, C, Z, X, Y).permute(0, 1, 3, 4, 2).reshape(*lead, C, X, Y, Z)
    if not t.dtype.is_floating_point:
        out = out.round().clamp(torch.iinfo(t.dtype).min, torch.iinfo(t.dtype).max)
    out = out.to(t.dtype)
    return out if is_t else out.numpy()


def _nearest_columns(affine, X: int, Y: int):
    """(X*Y,) the flat x-y source column of each output column under ``grid_sample``'s nearest rule, -1 outside.

    grid_sample itself picks them, from an image of column numbers (exact in float32 up to 2^24), so
    the gather that moves the columns makes the choices nearest resampling every slice would make,
    while touching each voxel once in its own dtype instead of resampling every z slice of every channel
    in float (the training step it made cheaper: docs/results/model.md, "What a CPU training step costs")."""
    import torch.nn.functional as F

    numbers = torch.arange(1, X * Y + 1, dtype=torch.float32, device=affine.device).reshape(1, 1, X, Y)
    coords = F.affine_grid(affine, [1, 1, X, Y], align_corners=False)
    picked = F.grid_sample(numbers, coords, mode="nearest", padding_mode="zeros", align_corners=False)
    return picked.reshape(-1).long() - 1


def _gather_columns(t, columns):
    """(..., C, X, Y, Z) with output column q = input column ``columns[q]`` (empty where it is -1)."""
    *lead, C, X, Y, Z = t.shape
    flat = t.contiguous().reshape(*lead, C, X * Y, Z)
    # A column moves as 8-byte words where its bytes allow: indexing copies a 64-voxel uint8 column
    # faster as 8 words than as 64 elements.
    if (Z * t.element_size()) % 8 == 0 and (flat.storage_offset() * t.element_size()) % 8 == 0:
        flat = flat.view(torch.int64)
    out = flat[..., columns.clamp(min=0), :]
    out.masked_fill_((columns < 0)[:, None], 0)
    return out.view(t.dtype).reshape(t.shape)
