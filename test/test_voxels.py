"""The voxeliser: exact cells and colours on constructed scenes, boundaries, clean-up, rotation, speed path."""

import json
import math

import numpy as np
import pytest

from equidiff_core import geometry
from equidiff_core.config import Workspace, default_config_dir, load_lab_config
from equidiff_core.perception.voxels import (
    VoxelError,
    Voxelizer,
    VoxelizerConfig,
    voxelize,
    voxelize_reference,
)

# Power-of-two voxel size and exactly representable corners: boundary tests are exact.
WS = Workspace(center=(0.5, 0.0, 0.25), edge=0.5, resolution=64)  # size 2^-7, lower (0.25, -0.25, 0)
SIZE = WS.voxel_size
IDENTITY = np.eye(4)


def _cloud(points, colors):
    return np.asarray(points, np.float32), np.asarray(colors, np.uint8).reshape(-1, 3)


def _center(i, j, k):
    return WS.lower + (np.array([i, j, k]) + 0.5) * SIZE


def _lab():
    return load_lab_config(default_config_dir() / "lab.yaml")


def _camera_cloud(T, base_points, colors):
    """Express base-frame points in the camera frame of pose T (float64 math, float32 out)."""
    return ((np.asarray(base_points) - T[:3, 3]) @ T[:3, :3]).astype(np.float32), colors


def test_points_land_in_the_documented_voxels_with_their_colours():
    pts = [_center(0, 0, 0), _center(63, 0, 5), _center(10, 20, 30), _center(1, 2, 3)]
    cols = [(255, 0, 0), (0, 255, 0), (1, 2, 3), (250, 128, 7)]
    grid = voxelize([_cloud(pts, cols)], [IDENTITY], WS)
    assert grid.shape == (4, 64, 64, 64) and grid.dtype == np.uint8
    occupied = np.argwhere(grid[0] > 0)
    assert sorted(map(tuple, occupied)) == sorted([(0, 0, 0), (63, 0, 5), (10, 20, 30), (1, 2, 3)])
    assert set(np.unique(grid[0])) == {0, 255}
    for (i, j, k), col in zip([(0, 0, 0), (63, 0, 5), (10, 20, 30), (1, 2, 3)], cols):
        assert tuple(grid[1:, i, j, k]) == col
    assert grid[1:, grid[0] == 0].max() == 0  # empty voxels carry no colour


def test_mean_colour_is_integer_mean_rounded_half_up():
    p = _center(5, 6, 7)
    jitter = np.array([[0, 0, 0], [0.3, -0.3, 0.2]]) * SIZE
    grid = voxelize([_cloud(p + jitter, [(0, 0, 0), (1, 3, 255)])], [IDENTITY], WS)
    # (0+1+1)//2 = 1, (0+3+1)//2 = 2, (0+255+1)//2 = 128
    assert tuple(grid[:, 5, 6, 7]) == (255, 1, 2, 128)
    three = voxelize([_cloud([p] * 3, [(10, 0, 0), (10, 0, 0), (11, 0, 1)])], [IDENTITY], WS)
    assert tuple(three[1:, 5, 6, 7]) == (10, 0, 0)  # 31/3 = 10.33 -> 10, 1/3 -> 0


def test_workspace_is_half_open_lower_inclusive_upper_exclusive():
    lo, hi = WS.lower, WS.upper
    just_below_hi = hi - 2.0**-12  # 0.03 voxel inside, exact in float32 all the way
    pts = np.array(
        [
            lo,  # exactly the minimum corner -> voxel (0, 0, 0)
            hi,  # exactly the maximum corner -> outside
            [hi[0], 0.0, 0.25],  # on the upper x face -> outside
            [lo[0], 0.0, 0.25],  # on the lower x face -> inside, i = 0
            just_below_hi,  # a hair inside the maximum corner -> voxel (63, 63, 63)
            lo - [1e-6, 0, 0],  # a hair below the lower x face -> outside
            [0.5, 0.0, lo[2] + 32 * SIZE],  # exactly on an inner face -> the upper cell (floor)
        ]
    )
    grid = voxelize([_cloud(pts, np.full((len(pts), 3), 9))], [IDENTITY], WS)
    occupied = sorted(map(tuple, np.argwhere(grid[0] > 0)))
    assert occupied == sorted([(0, 0, 0), (0, 32, 32), (63, 63, 63), (32, 32, 32)])
    np.testing.assert_array_equal(grid, voxelize_reference([_cloud(pts, np.full((len(pts), 3), 9))], [IDENTITY], WS))


def test_empty_and_fully_outside_input_give_an_empty_grid():
    empty = _cloud(np.zeros((0, 3)), np.zeros((0, 3)))
    outside = _cloud([[5.0, 5.0, 5.0], [-1.0, 0.0, 0.0]], [(1, 1, 1), (2, 2, 2)])
    for clouds in ([empty], [outside], [empty, outside]):
        ext = [IDENTITY] * len(clouds)
        vox = Voxelizer(WS, ext)
        grid = vox(clouds)
        assert grid.shape == (4, 64, 64, 64) and not grid.any()
        assert vox.last_stats.points_used == 0 and vox.last_stats.occupied == 0


def test_non_finite_points_never_land():
    pts = [[np.nan, 0.0, 0.1], [np.inf, 0.0, 0.1], [0.5, -np.inf, 0.1], _center(3, 3, 3)]
    grid = voxelize([_cloud(pts, [(1, 1, 1)] * 4)], [IDENTITY], WS)
    assert np.argwhere(grid[0]).tolist() == [[3, 3, 3]]


def test_extrinsics_move_camera_points_into_the_base_frame():
    lab = _lab()
    ws = lab.workspace
    rng = np.random.default_rng(3)
    cells = rng.integers(0, ws.resolution, (200, 3))
    base = ws.lower + (cells + 0.5) * ws.voxel_size  # voxel centres: far from any face
    colors = rng.integers(0, 256, (200, 3), dtype=np.uint8)
    exts = [c.extrinsics.matrix() for c in lab.cameras]
    clouds = [_camera_cloud(T, base[i::3], colors[i::3]) for i, T in enumerate(exts)]
    grid = voxelize(clouds, exts, ws)
    expected = np.zeros_like(grid)
    for (i, j, k), col in zip(
        np.concatenate([cells[0::3], cells[1::3], cells[2::3]]),
        np.concatenate([colors[0::3], colors[1::3], colors[2::3]]),
    ):
        expected[0, i, j, k] = 255
        expected[1:, i, j, k] = col  # cells may repeat; recompute the mean below
    uniq, inverse = np.unique(cells, axis=0, return_inverse=True)
    for u_idx, cell in enumerate(uniq):
        members = colors[inverse.ravel() == u_idx].astype(np.int64)
        expected[1:, cell[0], cell[1], cell[2]] = (members.sum(0) + len(members) // 2) // len(members)
    np.testing.assert_array_equal(grid, expected)


@pytest.mark.parametrize("quarter_turns", [1, 2, 3])
def test_rotating_the_scene_about_the_workspace_centre_rotates_the_grid(quarter_turns):
    lab = _lab()
    ws = lab.workspace
    theta = quarter_turns * math.pi / 2
    rng = np.random.default_rng(quarter_turns)
    cells = rng.integers(0, ws.resolution, (3000, 3))
    base = ws.lower + (cells + rng.uniform(0.2, 0.8, cells.shape)) * ws.voxel_size
    colors = rng.integers(0, 256, (3000, 3), dtype=np.uint8)
    exts = [c.extrinsics.matrix() for c in lab.cameras]
    clouds = [_camera_cloud(T, base[i::3], colors[i::3]) for i, T in enumerate(exts)]
    grid = voxelize(clouds, exts, ws)
    assert grid[0].sum() > 0
    # (a) the points move, the cameras stay
    Rz = geometry.rotz_pose(theta, center=ws.center)
    rotated = base @ Rz[:3, :3].T + Rz[:3, 3]
    moved = [_camera_cloud(T, rotated[i::3], colors[i::3]) for i, T in enumerate(exts)]
    np.testing.assert_array_equal(voxelize(moved, exts, ws), geometry.rotate_voxel_grid(grid, theta))
    # (b) the whole rig (cameras and scene) rotates: same camera-frame points, rotated extrinsics
    np.testing.assert_array_equal(voxelize(clouds, [Rz @ T for T in exts], ws), geometry.rotate_voxel_grid(grid, theta))


def _awkward_scene(seed):
    """Random clouds with every hard case: boundaries, faces, crowding, NaN, empty cloud."""
    lab = _lab()
    ws = lab.workspace
    rng = np.random.default_rng(seed)
    exts = [c.extrinsics.matrix() for c in lab.cameras]
    clouds = []
    for i, T in enumerate(exts):
        n = [20_000, 0, 5_000][i] if seed % 2 else 15_000
        base = rng.uniform(ws.lower - 0.05, ws.upper + 0.05, (n, 3))
        if n:
            face = rng.integers(0, ws.resolution + 1, (n // 4, 3))
            base[: n // 4] = ws.lower + face * ws.voxel_size  # exactly on voxel faces (in float64)
            base[n // 4 : n // 4 + 600] = np.asarray(ws.center) + 0.001  # 600 points in one voxel: crowded path
        pts, cols = _camera_cloud(T, base, rng.integers(0, 256, (n, 3), dtype=np.uint8))
        if n:
            pts[:7] = np.nan
        clouds.append((pts, cols))
    return clouds, exts, ws


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize(
    "cfg",
    [VoxelizerConfig(), VoxelizerConfig(table_z=0.03), VoxelizerConfig(min_depth=0.5, max_depth=0.9)],
    ids=["plain", "table", "depth"],
)
def test_fast_path_equals_reference_bit_for_bit(seed, cfg):
    clouds, exts, ws = _awkward_scene(seed)
    vox = Voxelizer(ws, exts, cfg)
    fast = vox(clouds)
    ref = voxelize_reference(clouds, exts, ws, cfg)
    np.testing.assert_array_equal(fast, ref)
    assert vox.last_stats.max_points_per_voxel >= 600  # the crowded fallback really ran
    # reusing the voxeliser (scratch buffers) with a smaller input gives the same as fresh
    half = [(p[: len(p) // 2], c[: len(c) // 2]) for p, c in clouds]
    np.testing.assert_array_equal(vox(half), voxelize_reference(half, exts, ws, cfg))


def test_fast_path_equals_reference_with_outlier_removal():
    clouds, exts, ws = _awkward_scene(4)
    small = [(p[:2000], c[:2000]) for p, c in clouds]
    cfg = VoxelizerConfig(outlier_neighbors=8, outlier_std_ratio=1.0)
    np.testing.assert_array_equal(Voxelizer(ws, exts, cfg)(small), voxelize_reference(small, exts, ws, cfg))


def test_clean_up_steps_remove_what_they_promise():
    rng = np.random.default_rng(5)
    cluster = _center(30, 30, 30) + rng.normal(0, 0.004, (400, 3))
    lonely = _center(5, 60, 40)
    low = _center(40, 40, 1)  # z = 1.5 voxels above the bottom face
    pts = np.vstack([cluster, lonely, low])
    cols = np.full((len(pts), 3), 100)
    base = voxelize([_cloud(pts, cols)], [IDENTITY], WS)
    assert base[0, 5, 60, 40] and base[0, 40, 40, 1]
    sor = voxelize([_cloud(pts, cols)], [IDENTITY], WS, VoxelizerConfig(outlier_neighbors=10))
    assert not sor[0, 5, 60, 40] and sor[0, 30, 30, 30]
    table = voxelize([_cloud(pts, cols)], [IDENTITY], WS, VoxelizerConfig(table_z=float(WS.lower[2] + 2 * SIZE)))
    assert not table[0, 40, 40, 1] and table[0, 30, 30, 30] and table[0, 5, 60, 40]
    # depth limits act on the camera-frame z (here the identity camera: z itself)
    near = voxelize([_cloud(pts, cols)], [IDENTITY], WS, VoxelizerConfig(max_depth=0.1))
    assert np.argwhere(near[0]).tolist() == [[40, 40, 1]]


def test_bad_inputs_raise_clear_errors():
    ok = _cloud([_center(1, 1, 1)], [(1, 2, 3)])
    with pytest.raises(VoxelError, match="expected 2 clouds"):
        voxelize([ok], [IDENTITY, IDENTITY], WS)
    with pytest.raises(VoxelError, match=r"points must be \(N, 3\)"):
        voxelize([(np.zeros((4, 2), np.float32), np.zeros((4, 2), np.uint8))], [IDENTITY], WS)
    with pytest.raises(VoxelError, match="colors must be uint8"):
        voxelize([(ok[0], ok[1].astype(np.float32))], [IDENTITY], WS)
    with pytest.raises(VoxelError, match="4x4"):
        Voxelizer(WS, [np.eye(3)])
    with pytest.raises(ValueError, match="min_depth"):
        VoxelizerConfig(min_depth=1.0, max_depth=0.5)


def test_bench_voxelize_prints_one_json_line(capsys):
    import argparse

    from equidiff_ros.commands import bench_voxelize

    parser = argparse.ArgumentParser()
    bench_voxelize.add_arguments(parser)
    args = parser.parse_args(["--points", "20000", "--repeats", "3", "--open3d-repeats", "1"])
    assert bench_voxelize.run(args) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 1
    result = json.loads(lines[0])
    for key in ("median_ms", "p95_ms", "open3d_median_ms", "speedup_vs_open3d"):
        assert isinstance(result[key], (int, float)) and result[key] > 0, key
    assert result["reference_equal"] is True
    assert result["points_per_camera"] == 20000 and result["cameras"] == 3
    assert 0 < result["points_in_workspace"] < 60000


def test_dense_grid_path_equals_reference():
    """Over half the voxels occupied switches the aggregation to whole-array arithmetic."""
    from equidiff_core.benches.voxelize import synthetic_scene

    lab = _lab()
    exts = [c.extrinsics.matrix() for c in lab.cameras]
    clouds = synthetic_scene(lab, 250_000, seed=11, kind="uniform")
    pts, cols = clouds[0]
    crowd = _camera_cloud(
        exts[0],
        np.tile(np.asarray(lab.workspace.center) + 0.001, (700, 1)),
        np.random.default_rng(2).integers(0, 256, (700, 3), dtype=np.uint8),
    )
    clouds[0] = (np.vstack([pts, crowd[0]]), np.vstack([cols, crowd[1]]))
    vox = Voxelizer(lab.workspace, exts)
    grid = vox(clouds)
    assert vox.last_stats.occupied > lab.workspace.resolution**3 // 2  # the dense path ran
    assert vox.last_stats.max_points_per_voxel >= 700  # with a crowded voxel
    assert vox.last_stats.occupied == int(np.count_nonzero(grid[0]))
    np.testing.assert_array_equal(grid, voxelize_reference(clouds, exts, lab.workspace))


def test_bench_voxelize_prints_one_json_line_and_exits_0_when_the_grid_equals_the_reference(capsys):
    from equidiff_ros.cli import main

    argv = ["bench", "voxelize", "--points", "2000", "--repeats", "2", "--no-open3d", "--scene", "uniform"]
    assert main(argv) == 0
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert result["reference_equal"] is True and result["points_per_camera"] == 2000 and result["repeats"] == 2
    assert result["open3d_median_ms"] is None and result["scene"] == "uniform"
