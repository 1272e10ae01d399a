"""Fusing three camera clouds into the voxel grid, timed against open3d (``equidiff bench voxelize``; the
command's help text lists the JSON keys; ``run_voxelize_bench`` takes its ``VoxelizeSettings`` and returns the JSON
line as a dict). ``synthetic_scene`` is the ray-cast input the perception tests share."""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from equidiff_core.config import default_config_dir, load_lab_config
from equidiff_core.perception.voxels import Voxelizer, voxelize_reference


def synthetic_scene(lab, n_points: int, seed: int = 0, kind: str = "raycast"):
    """One (points (N,3) float32 optical frame, colors (N,3) uint8) per camera of ``lab``."""
    rng = np.random.default_rng(seed)
    ws = lab.workspace
    clouds = []
    for cam in lab.cameras:
        T = cam.extrinsics.matrix()
        if kind == "uniform":
            base = rng.uniform(ws.lower - 0.1 * ws.edge, ws.upper + 0.1 * ws.edge, (n_points, 3))
            colors = rng.integers(0, 256, (n_points, 3), dtype=np.uint8)
        else:
            base, colors = _raycast(T, n_points, ws, rng)
        optical = (base - T[:3, 3]) @ T[:3, :3]
        clouds.append((np.ascontiguousarray(optical, dtype=np.float32), colors))
    return clouds


def _raycast(T, n_points: int, ws, rng):
    """Points a depth camera at pose T sees of a table with three boxes in a room (base frame)."""
    width = 640
    height = -(-n_points // width) + 1
    fx = (width / 2) / np.tan(np.radians(87 / 2))  # D455 colour HFOV ~87 deg
    u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    rays_cam = np.stack([(u - width / 2) / fx, (v - height / 2) / fx, np.ones_like(u)], -1).reshape(-1, 3)
    origin = T[:3, 3]
    rays = rays_cam @ T[:3, :3].T  # base-frame directions, optical z = 1
    cx, cy, _cz = ws.center
    table_z = ws.lower[2] + 0.02
    boxes = [  # (lower, upper, colour)
        (np.array([cx - 0.06, cy - 0.10, table_z]), np.array([cx + 0.02, cy - 0.02, table_z + 0.08]), (200, 40, 40)),
        (np.array([cx + 0.05, cy + 0.04, table_z]), np.array([cx + 0.11, cy + 0.12, table_z + 0.05]), (40, 160, 60)),
        (np.array([cx - 0.15, cy + 0.05, table_z]), np.array([cx - 0.10, cy + 0.10, table_z + 0.15]), (50, 70, 200)),
    ]
    room_lo, room_hi = np.array([-1.5, -2.0, table_z - 0.8]), np.array([2.5, 2.0, 2.5])
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / rays
        t_room = np.minimum.reduce(np.maximum((room_lo - origin) * inv, (room_hi - origin) * inv), axis=1)
        t_table = np.where(rays[:, 2] < 0, (table_z - origin[2]) / rays[:, 2], np.inf)
        depth = np.minimum(t_room, t_table)
        colors = np.where((t_table <= t_room)[:, None], np.array([150, 110, 70]), np.array([190, 190, 185]))
        for lo, hi, col in boxes:
            t1, t2 = (lo - origin) * inv, (hi - origin) * inv
            t_near = np.minimum(t1, t2).max(axis=1)
            t_far = np.maximum(t1, t2).min(axis=1)
            hit = (t_near <= t_far) & (t_near > 0) & (t_near < depth)
            depth = np.where(hit, t_near, depth)
            colors = np.where(hit[:, None], np.array(col), colors)
    depth = depth + rng.normal(0.0, 1.0, depth.shape) * 0.001 * depth**2  # ~1 mm at 1 m
    points = origin + rays * depth[:, None]
    colors = np.clip(colors + rng.normal(0, 6, colors.shape), 0, 255).astype(np.uint8)
    return points[:n_points], colors[:n_points]


def _timed(fn, repeats: int) -> tuple[list[float], list[float]]:
    """(wall ms, process CPU ms) per call."""
    wall, cpu = [], []
    for _ in range(repeats):
        c0, t0 = time.process_time(), time.perf_counter()
        fn()
        wall.append((time.perf_counter() - t0) * 1e3)
        cpu.append((time.process_time() - c0) * 1e3)
    return wall, cpu


@dataclass(frozen=True)
class VoxelizeSettings:
    """``equidiff bench voxelize``'s settings: its flags, same names (the command's help says more)."""

    points: int  # points per camera
    repeats: int  # timed calls of our voxeliser
    open3d_repeats: int  # timed calls of open3d
    scene: str  # raycast or uniform
    lab_config: Path | None  # lab.yaml (None: the installed one)
    seed: int
    open3d: bool  # also time the open3d baseline (``--no-open3d``: False)


def run_voxelize_bench(settings: VoxelizeSettings) -> dict:
    """The timings: the bench's JSON line (``reference_equal`` False when the grid differs from the
    reference: the command exits 1)."""
    lab = load_lab_config(settings.lab_config or default_config_dir() / "lab.yaml")
    ws = lab.workspace
    extrinsics = [c.extrinsics.matrix() for c in lab.cameras]
    clouds = synthetic_scene(lab, settings.points, settings.seed, settings.scene)
    voxelizer = Voxelizer(ws, extrinsics)
    grid = voxelizer(clouds)  # warm-up: sizes the scratch buffers
    times, cpu = _timed(lambda: voxelizer(clouds), settings.repeats)
    stats = voxelizer.last_stats
    t0 = time.perf_counter()
    reference = voxelize_reference(clouds, extrinsics, ws)
    reference_ms = (time.perf_counter() - t0) * 1e3
    result = {
        "median_ms": round(float(np.median(times)), 3),
        "p95_ms": round(float(np.percentile(times, 95)), 3),
        "open3d_median_ms": None,
        "speedup_vs_open3d": None,
        "cpu_median_ms": round(float(np.median(cpu)), 3),
        "reference_ms": round(reference_ms, 1),
        "reference_equal": bool(np.array_equal(grid, reference)),
        "cameras": len(clouds),
        "points_per_camera": settings.points,
        "scene": settings.scene,
        "points_in_workspace": stats.points_used,
        "occupied_voxels": stats.occupied,
        "resolution": ws.resolution,
        "repeats": settings.repeats,
        "load_avg_1min": round(os.getloadavg()[0], 2),
        "cpu_count": os.cpu_count(),
    }
    if settings.open3d:
        pcd = _open3d_cloud(clouds, extrinsics)
        o3d_times, _ = _timed(lambda: _open3d_grid(pcd, ws), settings.open3d_repeats)
        result["open3d_median_ms"] = round(float(np.median(o3d_times)), 3)
        result["speedup_vs_open3d"] = round(result["open3d_median_ms"] / result["median_ms"], 1)
    return result


def _open3d_cloud(clouds, extrinsics):
    """The same points as an open3d cloud in the base frame (prepared outside the timing)."""
    import open3d as o3d  # an optional extra (the baseline only): imported when the baseline runs

    pts = np.concatenate([(p.astype(np.float64) @ T[:3, :3].T) + T[:3, 3] for (p, _), T in zip(clouds, extrinsics)])
    cols = np.concatenate([c for _, c in clouds]).astype(np.float64) / 255.0
    pcd = o3d.geometry.PointCloud()
    pcd.points = o3d.utility.Vector3dVector(pts)
    pcd.colors = o3d.utility.Vector3dVector(cols)
    return pcd


def _open3d_grid(pcd, ws):
    import open3d as o3d  # see _open3d_cloud

    return o3d.geometry.VoxelGrid.create_from_point_cloud_within_bounds(pcd, ws.voxel_size, ws.lower, ws.upper)
