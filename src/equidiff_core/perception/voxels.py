"""Fuse coloured point clouds into the policy's (4, R, R, R) uint8 voxel grid (no ROS).

Grid contract (docs/architecture.md): arrays are indexed ``(channel, x, y, z)`` in the robot
base frame, voxel ``(i, j, k)`` spans ``lower + (i, j, k)·size`` to ``lower + (i+1, j+1,
k+1)·size`` with ``lower = workspace.lower`` and ``size = workspace.voxel_size``, so index 0
sits at the workspace minimum and ``geometry.rotate_voxel_grid`` (rot90 with x -> y, about
the grid centre) is the same rotation as ``geometry.rotate_action`` about the workspace
centre. Channel 0 is occupancy (255 where at least one point falls, else 0); channels 1-3
are the mean R, G, B of the points in the voxel, rounded half up in integers:
``(sum + count // 2) // count`` (0 where empty).

Where a point lands, exactly. Each camera's rigid transform and the scaling to voxel units
are fused into one affine map ``u = A·p + c`` with ``A = float32(R_base_cam / size)`` and
``c = float32((t_base_cam - lower) / size)``; ``u`` is evaluated in float32 in this order:
``u_i = ((A_i0·x + A_i1·y) + A_i2·z) + c_i``, and the point goes to voxel ``floor(u)``
if ``0 <= floor(u) < R`` on every axis, i.e. the half-open cube ``[lower, upper)``. Being
plain IEEE float32 operations, this is reproducible bit for bit by any implementation that
follows it (``voxelize_reference`` does, in the most direct way). NaN/inf points never land.

Optional clean-up, each skipped entirely (no cost) when disabled, applied in this order:
camera-frame depth limits, table removal (points whose base-frame height is below
``table_z``), statistical outlier removal (Open3D's definition: mean distance to the
``outlier_neighbors`` nearest neighbours beyond the global mean + ``outlier_std_ratio``
standard deviations) on the points inside the workspace only.

Speed (``equidiff bench voxelize``): the fast path is numpy only and single-threaded (threads
did not pay on a shared machine with few cores). The ``Voxelizer`` keeps its per-point scratch buffers
between calls: page faults on fresh 10 MB temporaries cost more than the arithmetic. Each
camera's points are transformed and tested, and only those that land are gathered (most of a
real frame lies outside the workspace). The colour means come
from two weighted ``np.bincount`` passes on packed integers that are exact in float64: the
first sums ``R + B·2^16`` (exact while a voxel holds <= 257 points, otherwise the affected
sums are recomputed per channel), the second ``G·2^20 + 1``, which yields the G sum and the
point count at once (exact while the cloud holds < 2^20 points, else counted separately).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..config import Workspace

_RB_MAX_COUNT = 257  # 257 * 255 < 2^16: R sums stay below the B field of R + B*2^16
_COUNT_BITS = 20  # G*2^20 + 1: the count lives in the low 20 bits


class VoxelError(ValueError):
    """Inputs the voxeliser cannot use (wrong shapes or dtypes, wrong number of clouds)."""


@dataclass(frozen=True)
class VoxelizerConfig:
    """Optional clean-up steps; the defaults (all off) keep the hot path minimal."""

    min_depth: float | None = None  # m, camera-frame z; nearer points are dropped
    max_depth: float | None = None  # m, camera-frame z; farther points are dropped
    table_z: float | None = None  # m, base frame; points below this height are dropped
    outlier_neighbors: int = 0  # statistical outlier removal: k nearest neighbours (0 = off)
    outlier_std_ratio: float = 2.0

    def __post_init__(self):
        if self.min_depth is not None and self.max_depth is not None and self.min_depth >= self.max_depth:
            raise ValueError(f"min_depth {self.min_depth} must be below max_depth {self.max_depth}")
        if self.outlier_neighbors < 0:
            raise ValueError(f"outlier_neighbors must be >= 0, got {self.outlier_neighbors}")
        if self.outlier_std_ratio <= 0:
            raise ValueError(f"outlier_std_ratio must be positive, got {self.outlier_std_ratio}")


@dataclass(frozen=True)
class VoxelStats:
    """What the last call saw, for diagnostics."""

    points_in: int  # points given, all cameras
    points_used: int  # points that landed in the grid (after clean-up)
    occupied: int  # occupied voxels
    max_points_per_voxel: int


# --- The shared definition -----------------------------------------------------------------


def voxel_affine(T_base_cam: np.ndarray, workspace: Workspace) -> tuple[np.ndarray, np.ndarray]:
    """(A, c) float32 with u = A·p + c the voxel-unit coordinates of camera-frame point p."""
    T = np.asarray(T_base_cam, dtype=np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise VoxelError(f"extrinsics must be a finite 4x4 matrix, got shape {T.shape}")
    size = workspace.voxel_size
    A = (T[:3, :3] / size).astype(np.float32)
    c = ((T[:3, 3] - workspace.lower) / size).astype(np.float32)
    return A, c


def table_threshold(table_z: float, workspace: Workspace) -> np.float32:
    """``table_z`` (m, base frame) in voxel units: points with u_z below it are dropped."""
    return np.float32((table_z - workspace.lower[2]) / workspace.voxel_size)


def _as_cloud(cloud: Any, where: str) -> tuple[np.ndarray, np.ndarray]:
    """(points, colors) from a tuple or anything with .points/.colors (CloudFrame, pointcloud.Cloud)."""
    points, colors = (cloud.points, cloud.colors) if hasattr(cloud, "points") else cloud
    points = np.asarray(points)
    colors = np.asarray(colors)
    if points.ndim != 2 or points.shape[1] != 3:
        raise VoxelError(f"{where}: points must be (N, 3), got {points.shape}")
    if colors.shape != points.shape:
        raise VoxelError(f"{where}: colors {colors.shape} must match points {points.shape}")
    if colors.dtype != np.uint8:
        raise VoxelError(f"{where}: colors must be uint8, got {colors.dtype}")
    if points.dtype != np.float32:
        points = points.astype(np.float32)
    return np.ascontiguousarray(points), np.ascontiguousarray(colors)


def _statistical_inliers(positions: np.ndarray, k: int, std_ratio: float) -> np.ndarray:
    """Boolean mask of points whose mean distance to their k neighbours is not an outlier.

    Same rule as Open3D's ``remove_statistical_outlier``; scipy's cKDTree does the search.
    """
    n = len(positions)
    if n <= k:
        return np.ones(n, dtype=bool)
    from scipy.spatial import cKDTree

    dist, _ = cKDTree(positions).query(positions, k=k + 1)
    mean_dist = dist[:, 1:].mean(axis=1)
    return mean_dist <= mean_dist.mean() + std_ratio * mean_dist.std()


def _check_inputs(clouds: Sequence[Any], n_cameras: int) -> list[tuple[np.ndarray, np.ndarray]]:
    if len(clouds) != n_cameras:
        raise VoxelError(f"expected {n_cameras} clouds (one per extrinsics), got {len(clouds)}")
    return [_as_cloud(c, f"cloud {i}") for i, c in enumerate(clouds)]


# --- Fast path -----------------------------------------------------------------------------


class Voxelizer:
    """Voxelise clouds from fixed cameras: ``grid = Voxelizer(ws, [T_base_cam, ...])(clouds)``.

    Keeps its scratch buffers between calls, so build one per stream and reuse it (not
    thread-safe). ``clouds[i]`` is ``(points (N,3) float32, colors (N,3) uint8)`` or an
    object with ``.points``/``.colors`` in camera i's optical frame.
    """

    def __init__(self, workspace: Workspace, extrinsics: Sequence[np.ndarray], config: VoxelizerConfig | None = None):
        if len(extrinsics) == 0:
            raise VoxelError("at least one camera extrinsics is required")
        self.workspace = workspace
        self.config = config or VoxelizerConfig()
        self._affine = [voxel_affine(T, workspace) for T in extrinsics]
        R = workspace.resolution
        if R**3 >= 2**31:
            raise VoxelError(f"resolution {R} too large for int32 voxel indices")
        self._capacity = 0
        self._camera_capacity = 0
        self.last_stats: VoxelStats | None = None

    def _reserve(self, n_total: int, n_camera: int) -> None:
        if n_total > self._capacity:
            cap = max(n_total, int(self._capacity * 1.25))
            self._u = np.empty((3, cap), np.float32)
            self._iu = np.empty((3, cap), np.int32)
            self._lin = np.empty(cap, np.int32)
            self._lin_tmp = np.empty(cap, np.int32)
            self._rgb = np.empty(cap, np.uint32)
            self._capacity = cap
        if n_camera > self._camera_capacity:
            cap = max(n_camera, int(self._camera_capacity * 1.25))
            self._columns = np.empty((3, cap), np.float32)
            self._u_camera = np.empty((3, cap), np.float32)
            self._tmp = np.empty(cap, np.float32)
            self._mask = np.empty(cap, bool)
            self._mask_tmp = np.empty(cap, bool)
            self._rgb_camera = np.empty(cap, np.uint32)
            self._camera_capacity = cap

    def __call__(self, clouds: Sequence[Any]) -> np.ndarray:
        cfg = self.config
        R = self.workspace.resolution
        clouds = _check_inputs(clouds, len(self._affine))
        sizes = [len(p) for p, _ in clouds]
        self._reserve(max(sum(sizes), 1), max(*sizes, 1))
        # 1. Per camera: the exact transform of every point, the exact in-grid test (plus the
        #    optional depth and table limits), then keep only the points that land.
        off = 0
        for (points, colors), (A, c) in zip(clouds, self._affine):
            m = len(points)
            if m == 0:
                continue
            u_cam = self._u_camera[:, :m]
            with np.errstate(invalid="ignore", over="ignore"):  # NaN/inf points simply fail the test
                self._transform(points, A, c, u_cam)
                idx = np.flatnonzero(self._lands(points, u_cam))
            k = len(idx)
            np.take(u_cam, idx, axis=1, out=self._u[:, off : off + k])
            rgb_cam = self._rgb_camera[:m]
            _pack_rgb24(colors, rgb_cam)  # packing all and taking is cheaper than gathering (k, 3) rows
            np.take(rgb_cam, idx, out=self._rgb[off : off + k])
            off += k
        n = off
        u, iu, rgb = self._u[:, :n], self._iu[:, :n], self._rgb[:n]
        # 2. Cell indices: every kept u is in [0, R), where truncation is floor.
        np.copyto(iu, u, casting="unsafe")
        lin = self._lin[:n]
        np.multiply(iu[0], R * R, out=lin)
        np.multiply(iu[1], R, out=self._lin_tmp[:n])
        lin += self._lin_tmp[:n]
        lin += iu[2]
        if cfg.outlier_neighbors > 0 and n:
            positions = u.T.astype(np.float64) * self.workspace.voxel_size
            inliers = _statistical_inliers(positions, cfg.outlier_neighbors, cfg.outlier_std_ratio)
            lin, rgb = lin[inliers], rgb[inliers]
        # 3. Occupancy and mean colour.
        grid, occupied, max_count = _aggregate(lin, rgb, R)
        self.last_stats = VoxelStats(sum(sizes), len(lin), occupied, max_count)
        return grid

    def _transform(self, points: np.ndarray, A: np.ndarray, c: np.ndarray, u: np.ndarray) -> None:
        """The exact definition, operation by operation, on contiguous columns.

        Elementwise numpy on a transposed copy beats a BLAS matmul here: same speed
        single-threaded, deterministic (no FMA or summation-order differences) and immune to
        OpenBLAS spreading a 3x3 product over busy cores.
        """
        m = len(points)
        columns = self._columns[:, :m]
        np.copyto(columns, points.T)
        x, y, z = columns
        t = self._tmp[:m]
        for i in range(3):
            out = u[i]
            np.multiply(x, A[i, 0], out=out)
            np.multiply(y, A[i, 1], out=t)
            out += t
            np.multiply(z, A[i, 2], out=t)
            out += t
            out += c[i]

    def _lands(self, points: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Mask of points with 0 <= floor(u) < R on every axis (i.e. 0 <= u < R; NaN fails),
        within the configured depth limits and above the table."""
        cfg = self.config
        m = u.shape[1]
        R = np.float32(self.workspace.resolution)
        mask, t = self._mask[:m], self._mask_tmp[:m]
        np.greater_equal(u[0], 0, out=mask)
        for i in range(3):
            if i:
                mask &= np.greater_equal(u[i], 0, out=t)
            mask &= np.less(u[i], R, out=t)
        if cfg.table_z is not None:
            mask &= np.greater_equal(u[2], table_threshold(cfg.table_z, self.workspace), out=t)
        if cfg.min_depth is not None:
            mask &= np.greater_equal(points[:, 2], np.float32(cfg.min_depth), out=t)
        if cfg.max_depth is not None:
            mask &= np.less_equal(points[:, 2], np.float32(cfg.max_depth), out=t)
        return mask


def _pack_rgb24(colors: np.ndarray, out: np.ndarray) -> None:
    """(N, 3) uint8 RGB -> (N,) uint32 R | G << 8 | B << 16 without per-channel passes.

    Reads each point's three bytes plus the next point's first byte as one little-endian
    uint32 (a strided, unaligned view) and masks the fourth byte off.
    """
    n = len(colors)
    if n == 0:
        return
    flat = colors.reshape(-1)
    if n > 1:
        out[: n - 1] = np.ndarray((n - 1,), dtype="<u4", buffer=flat, offset=0, strides=(3,))
    last = colors[-1].astype(np.uint32)
    out[n - 1] = last[0] | (last[1] << 8) | (last[2] << 16)
    out &= np.uint32(0xFFFFFF)


def _aggregate(lin: np.ndarray, rgb: np.ndarray, R: int) -> tuple[np.ndarray, int, int]:
    """(grid, occupied voxels, max points per voxel) from linear voxel indices and packed RGB24."""
    nvox = R**3
    grid = np.zeros((4, nvox), np.uint8)
    if len(lin) == 0:
        return grid.reshape(4, R, R, R), 0, 0
    rb = np.bitwise_and(rgb, np.uint32(0xFF00FF))  # R + B*2^16
    sum_rb = np.bincount(lin, weights=rb, minlength=nvox)
    # Sparse grids (real scenes): work on the occupied voxels only. Dense ones (over half the
    # voxels occupied): whole contiguous arrays beat gathers and scatters.
    if len(lin) < 2**_COUNT_BITS:
        g1 = np.bitwise_and(rgb, np.uint32(0xFF00))
        g1 <<= np.uint32(_COUNT_BITS - 8)
        g1 |= np.uint32(1)  # G*2^20 + 1
        sum_g1 = np.bincount(lin, weights=g1, minlength=nvox)
        dense = np.count_nonzero(sum_g1) > nvox // 2
        idx = slice(None) if dense else np.flatnonzero(sum_g1)
        packed = sum_g1[idx].astype(np.int64)
        count = packed & ((1 << _COUNT_BITS) - 1)
        sum_g = packed >> _COUNT_BITS
    else:
        count_all = np.bincount(lin, minlength=nvox)
        dense = np.count_nonzero(count_all) > nvox // 2
        idx = slice(None) if dense else np.flatnonzero(count_all)
        count = count_all[idx]
        sum_g = np.bincount(lin, weights=(rgb >> 8) & 0xFF, minlength=nvox)[idx].astype(np.int64)
    packed = sum_rb[idx].astype(np.int64)
    sum_r = packed & 0xFFFF
    sum_b = packed >> 16
    crowded = count > _RB_MAX_COUNT
    if crowded.any():  # R overflowed into B for these voxels: recount them per channel
        sum_r[crowded] = np.bincount(lin, weights=rgb & 0xFF, minlength=nvox)[idx][crowded].astype(np.int64)
        sum_b[crowded] = np.bincount(lin, weights=rgb >> 16, minlength=nvox)[idx][crowded].astype(np.int64)
    # (sum + count // 2) // count via float64 true division: exact here (an integer quotient
    # comes out exactly; a non-integer a/b < 256 is >= 1/b away from the next integer, far
    # more than one rounding), and several times faster than numpy's int64 floor division.
    half = count >> 1
    if dense:
        occupied_mask = count > 0
        occupied = int(np.count_nonzero(occupied_mask))
        grid[0] = occupied_mask
        grid[0] *= 255
        count_f = np.maximum(count, 1).astype(np.float64)  # empty voxels: 0 / 1 = 0
    else:
        occupied = len(idx)
        grid[0, idx] = 255
        count_f = count.astype(np.float64)
    for ch, total in ((1, sum_r), (2, sum_g), (3, sum_b)):
        grid[ch, idx] = np.floor((total + half) / count_f)
    return grid.reshape(4, R, R, R), occupied, int(count.max())


def voxelize(
    clouds: Sequence[Any], extrinsics: Sequence[np.ndarray], workspace: Workspace, config: VoxelizerConfig | None = None
) -> np.ndarray:
    """One-shot ``Voxelizer(workspace, extrinsics, config)(clouds)``."""
    return Voxelizer(workspace, extrinsics, config)(clouds)


# --- Reference ------------------------------------------------------------------------------


def voxelize_reference(
    clouds: Sequence[Any], extrinsics: Sequence[np.ndarray], workspace: Workspace, config: VoxelizerConfig | None = None
) -> np.ndarray:
    """The definition in the module docstring written as directly as possible (slow, for tests).

    The fast path must equal this bit for bit.
    """
    cfg = config or VoxelizerConfig()
    R = workspace.resolution
    clouds = _check_inputs(clouds, len(extrinsics))
    cells, colors_kept, positions = [], [], []
    for (points, colors), T in zip(clouds, extrinsics):
        if cfg.min_depth is not None or cfg.max_depth is not None:
            z = points[:, 2]
            low = -np.inf if cfg.min_depth is None else cfg.min_depth
            high = np.inf if cfg.max_depth is None else cfg.max_depth
            keep = (z >= np.float32(low)) & (z <= np.float32(high))  # NaN compares False: dropped too
            points, colors = points[keep], colors[keep]  # noqa: PLW2901 - the camera's cloud, depth-limited
        A, c = voxel_affine(T, workspace)
        with np.errstate(invalid="ignore", over="ignore"):
            u = ((points[:, 0:1] * A[:, 0] + points[:, 1:2] * A[:, 1]) + points[:, 2:3] * A[:, 2]) + c
            cell = np.floor(u)
            inside = np.all((cell >= 0) & (cell < R), axis=1)
            if cfg.table_z is not None:
                inside &= u[:, 2] >= table_threshold(cfg.table_z, workspace)
        cells.append(cell[inside].astype(np.int64))
        colors_kept.append(colors[inside])
        positions.append(u[inside].astype(np.float64) * workspace.voxel_size)
    cell = np.concatenate(cells)
    colors = np.concatenate(colors_kept)
    if cfg.outlier_neighbors > 0 and len(cell):
        inliers = _statistical_inliers(np.concatenate(positions), cfg.outlier_neighbors, cfg.outlier_std_ratio)
        cell, colors = cell[inliers], colors[inliers]
    count = np.zeros((R, R, R), np.int64)
    sums = np.zeros((3, R, R, R), np.int64)
    np.add.at(count, (cell[:, 0], cell[:, 1], cell[:, 2]), 1)
    for ch in range(3):
        np.add.at(sums[ch], (cell[:, 0], cell[:, 1], cell[:, 2]), colors[:, ch].astype(np.int64))
    grid = np.zeros((4, R, R, R), np.uint8)
    occupied = count > 0
    grid[0][occupied] = 255
    for ch in range(3):
        grid[1 + ch][occupied] = (sums[ch][occupied] + count[occupied] // 2) // count[occupied]
    return grid
