"""Simulated D455s: clouds land where the objects are, with D455-like intrinsics, noise and dropout."""

import time

import mujoco
import numpy as np
import pytest

from equidiff_core.cameras.base import CameraError
from equidiff_core.cameras.twin import Intrinsics, TwinCamera, depth_to_points
from equidiff_core.config import default_config_dir, load_lab_config
from equidiff_core.twin import scene
from equidiff_core.twin.config import TwinConfig
from equidiff_core.twin.shared_state import StateWriter

CFG = TwinConfig()
LAB = load_lab_config(default_config_dir() / "lab.yaml")
WS = LAB.workspace


def _state(seed):
    model = scene.build_model(CFG)
    data = mujoco.MjData(model)
    data.qpos[:7] = CFG.sim.initial_q
    poses = scene.sample_scene(CFG.scene, seed)
    scene.apply_scene(model, data, poses, CFG.scene)
    return data.qpos.copy(), poses


def _grid(frames_and_cams):
    """Plain numpy voxelisation (occupancy + last colour) of clouds in their optical frames."""
    grid = np.zeros((4, WS.resolution, WS.resolution, WS.resolution), np.uint8)
    for frame, cam in frames_and_cams:
        T = cam.extrinsics.matrix()
        pts = frame.points.astype(np.float64) @ T[:3, :3].T + T[:3, 3]
        idx = np.floor((pts - WS.lower) / WS.voxel_size).astype(int)
        keep = np.all((idx >= 0) & (idx < WS.resolution), axis=1)
        i, j, k = idx[keep].T
        grid[0, i, j, k] = 255
        grid[1:, i, j, k] = frame.colors[keep].T
    return grid


def _voxel(xyz):
    return tuple(np.floor((np.asarray(xyz) - WS.lower) / WS.voxel_size).astype(int))


def _read_all(qpos, **options):
    frames = []
    for cam in LAB.cameras:
        with TwinCamera(cam, state_source=lambda t: (qpos, 1.0, 42), paced=False, **options) as c:
            frames.append((c.read(), cam))
    return frames


@pytest.mark.sim
def test_clouds_fill_the_voxels_where_the_objects_are():
    for seed in (3, 17):
        qpos, poses = _state(seed)
        grid = _grid(_read_all(qpos))
        bx, by = poses.block_xy
        top = _voxel((bx, by, CFG.scene.block_size[2] - 1e-3))  # the block's top face
        neighbourhood = grid[:, top[0] - 1 : top[0] + 2, top[1] - 1 : top[1] + 2, top[2]]
        assert neighbourhood[0].max() == 255, f"seed {seed}: no occupied voxel on the block's top"
        colors = neighbourhood[1:, neighbourhood[0] > 0].T
        assert (colors[:, 0] > 2 * colors[:, 1]).any(), "block voxels should be red"
        # nothing floats 8 cm above the block; the bowl's rim is seen where the bowl is
        above = _voxel((bx, by, 0.11))
        assert grid[0, above[0] - 1 : above[0] + 2, above[1] - 1 : above[1] + 2, above[2]].max() == 0
        rim = _voxel((poses.bowl_xy[0], poses.bowl_xy[1], 0.0))
        r = int(np.ceil(CFG.scene.bowl_outer_radius / WS.voxel_size)) + 1
        wall_z = int((CFG.scene.bowl_wall_height + CFG.scene.bowl_base_thickness - WS.lower[2]) / WS.voxel_size)
        bowl_region = grid[:, rim[0] - r : rim[0] + r + 1, rim[1] - r : rim[1] + r + 1, wall_z - 2 : wall_z + 1]
        blue = bowl_region[1:, bowl_region[0] > 0].T
        assert len(blue) > 20 and (blue[:, 2] > 2 * blue[:, 0]).sum() > 10


@pytest.mark.sim
def test_noise_free_points_are_exact_and_in_the_optical_frame():
    qpos, poses = _state(5)
    for frame, cam in _read_all(qpos, depth_noise=False, dropout=0.0):
        assert frame.stamp_ns == 42 and frame.points.dtype == np.float32 and frame.colors.dtype == np.uint8
        assert np.all(frame.points[:, 2] > 0)  # optical frame: z forward
        T = cam.extrinsics.matrix()
        pts = frame.points.astype(np.float64) @ T[:3, :3].T + T[:3, 3]
        # the table top (z = 0) is a plane: its points land on it to well under a millimetre
        away = (
            (np.hypot(*(pts[:, :2] - poses.block_xy).T) > 0.06)
            & (np.hypot(*(pts[:, :2] - poses.bowl_xy).T) > 0.1)
            & (pts[:, 0] > 0.3)
        )
        table = away & (np.abs(pts[:, 2]) < 0.004) & (np.hypot(pts[:, 0] - 0.45, pts[:, 1]) < 0.3)
        assert table.sum() > 1000
        assert np.abs(pts[table, 2]).max() < 1e-3
        # points on the block's top face lie at its height
        near = np.hypot(pts[:, 0] - poses.block_xy[0], pts[:, 1] - poses.block_xy[1]) < 0.008
        assert near.any()
        np.testing.assert_allclose(pts[near, 2].max(), CFG.scene.block_size[2], atol=1.5e-3)


def test_intrinsics_are_d455_like_and_backprojection_inverts_projection():
    intr = Intrinsics.from_fovy(848, 480, 58.0)
    hfov = 2 * np.degrees(np.arctan(intr.cx / intr.fx))
    assert 85 < hfov < 92  # D455 depth: 87 x 58 degrees
    depth = np.full((4, 6), 2.0, np.float32)
    small = Intrinsics.from_fovy(6, 4, 58.0)
    pts = depth_to_points(depth, small)
    u = pts[..., 0] * small.fx / pts[..., 2] + small.cx - 0.5
    v = pts[..., 1] * small.fy / pts[..., 2] + small.cy - 0.5
    vv, uu = np.indices(depth.shape)
    np.testing.assert_allclose(u, uu, atol=1e-5)
    np.testing.assert_allclose(v, vv, atol=1e-5)


@pytest.mark.sim
def test_noise_and_dropout_degrade_the_cloud_like_a_stereo_camera():
    qpos, _ = _state(5)
    cam = LAB.cameras[0]
    src = lambda t: (qpos, 0.0, 1)
    with TwinCamera(cam, state_source=src, paced=False, depth_noise=False, dropout=0.0) as clean_cam:
        clean = clean_cam.read()
    with TwinCamera(cam, state_source=src, paced=False, depth_noise=True, dropout=0.2) as noisy_cam:
        noisy = noisy_cam.read()
    lost = 1 - len(noisy.points) / len(clean.points)
    assert 0.18 < lost < 0.35, lost
    # same pixels, noisier depth: compare the depth spread on the table plane
    T = cam.extrinsics.matrix()

    def table_z(frame):
        pts = frame.points.astype(np.float64) @ T[:3, :3].T + T[:3, 3]
        return pts[(np.abs(pts[:, 2]) < 0.01) & (np.hypot(pts[:, 0] - 0.45, pts[:, 1]) < 0.2), 2]

    def mad(z):
        return np.median(np.abs(z - np.median(z)))

    assert mad(table_z(clean)) < 1e-4
    assert mad(table_z(noisy)) > 5e-4  # sigma(z ~ 0.8 m) ~ 1.5 mm


def test_bad_options_missing_twin_and_nan_state_are_clear_errors():
    cam = LAB.cameras[0]
    with pytest.raises(CameraError, match="unknown option"):
        TwinCamera(cam, exposure=3)
    with pytest.raises(CameraError, match="twin_node"):
        TwinCamera(cam, shm_name="equidiff_twin_nobody_home").connect()
    qpos, _ = _state(1)
    bad = qpos.copy()
    bad[0] = np.nan
    with (
        TwinCamera(cam, state_source=lambda t: (bad, 0.0, 1), paced=False) as c,
        pytest.raises(CameraError, match="NaN"),
    ):
        c.read()
    with pytest.raises(CameraError, match="not connected"):
        TwinCamera(cam, state_source=lambda t: (qpos, 0.0, 1)).read()


@pytest.mark.sim
def test_a_stalled_camera_times_out_like_a_stalled_usb_link_and_comes_back(tmp_path):
    """The safety bench's camera fault: while the flag exists, reads wait out their timeout and fail
    as a RealSense's do; once it is gone, frames come again."""
    cam, flag = LAB.cameras[0], tmp_path / "stall"
    qpos, _ = _state(1)
    with TwinCamera(cam, state_source=lambda t: (qpos, 1.0, 42), paced=False, stall_flag=str(flag)) as c:
        assert len(c.read().points) > 0
        flag.touch()
        t0 = time.monotonic()
        with pytest.raises(CameraError, match="no frame within 0.2 s"):
            c.read(timeout_s=0.2)
        assert time.monotonic() - t0 >= 0.2
        flag.unlink()
        assert len(c.read().points) > 0


@pytest.mark.sim
def test_reads_the_twin_state_from_shared_memory_and_paces_to_publish_hz():
    qpos, _poses = _state(8)
    name = f"equidiff_twin_camtest_{time.time_ns()}"
    writer = StateWriter(len(qpos), name)
    try:
        writer.write(qpos, 3.5, 1_700_000_000_123_456_789)
        cam = LAB.cameras[1]
        with TwinCamera(cam, shm_name=name, width=106, height=60) as c:
            frames = [c.read() for _ in range(3)]
            # paced reads show the snapshot nearest their wall-clock trigger tick
            period_ns = int(1e9 / cam.publish_hz)
            now = time.time_ns()
            for k in range(-3, 8):  # snapshots around the coming ticks, 10 ms after each
                writer.write(qpos, 4.0, (now // period_ns + k) * period_ns + 10_000_000)
            t0 = time.monotonic()
            f1, f2 = c.read(), c.read()
            period = (time.monotonic() - t0) / 2
        assert all(f.stamp_ns == 1_700_000_000_123_456_789 for f in frames)
        assert f1.stamp_ns % period_ns == 10_000_000 and f2.stamp_ns - f1.stamp_ns == period_ns
        assert period == pytest.approx(1 / cam.publish_hz, rel=0.5)
    finally:
        writer.close()


@pytest.mark.sim
def test_a_scene_renders_the_same_grid_whatever_the_recorder_rendered_before():
    """The in-process roll-outs and demos reset each camera's depth noise from the scene seed, so a
    seed's episode does not depend on the episodes before it; another seed draws other noise."""
    from equidiff_core.twin.demos import DirectRecorder

    def first_grid(rec, seed):
        rec.reset(seed)
        return rec.voxel_grid(0)

    fresh, used = DirectRecorder(CFG, LAB), DirectRecorder(CFG, LAB)
    try:
        assert CFG.render.depth_noise
        used.reset(3)
        for stamp in range(3):  # frames rendered before the scene draw from the noise stream
            used.voxel_grid(stamp)
        np.testing.assert_array_equal(first_grid(used, 7), first_grid(fresh, 7))
        again = first_grid(fresh, 7)
        np.testing.assert_array_equal(again, first_grid(used, 7))
        # the noise itself is drawn: the same scene under another seed's noise renders another grid
        other = fresh.voxel_grid(0)  # the stream moved on after one frame
        assert not np.array_equal(other, again)
    finally:
        fresh.close()
        used.close()
