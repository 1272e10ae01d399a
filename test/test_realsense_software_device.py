"""camera_node's RealSense backend through librealsense's own ``software_device``: real frames, real library.

A synthetic scene of known geometry (a table plane seen at 30 degrees, a box in front of it)
is ray-cast into a depth image (as a D455's depth module would see it) and a colour image (from
the colour module, 59 mm to the side and turned slightly), pushed through pyrealsense2 as
software-device frames, and read by ``RealSenseCamera`` with lab.yaml's options: the real
``rs.align`` to colour, decimation, spatial and temporal filters in disparity space, and our
deprojection. Every point of the cloud must lie on the scene, with the box's colour where it
lies on the box.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from helpers_realsense import SoftwareRealSense
from scipy.spatial.transform import Rotation

from equidiff_core.cameras import make_camera
from equidiff_core.cameras.realsense import RealSenseCamera
from equidiff_core.config import default_config_dir, load_lab_config
from equidiff_core.geometry import invert_pose, make_pose

pytest.importorskip("pyrealsense2")

LAB = load_lab_config(default_config_dir() / "lab.yaml")
FRONT = LAB.cameras[0]  # 848x480 @ 30, decimation 2, spatial, temporal, exposure 8500 us, white balance 4600 K
W, H = FRONT.width, FRONT.height
# D455-like intrinsics at 848x480: the colour module's field of view a little narrower than depth's
DEPTH_INTR = {"fx": 426.0, "fy": 426.0, "ppx": 423.7, "ppy": 238.4}
COLOR_INTR = {"fx": 610.0, "fy": 610.0, "ppx": 421.3, "ppy": 242.6}
# where the depth module sits in the colour optical frame (the frame of the cloud)
T_COLOR_DEPTH = make_pose(
    Rotation.from_euler("xyz", [0.3, -0.4, 0.2], degrees=True).as_matrix(), [0.059, 0.0004, -0.0003]
)

# The scene, in the colour optical frame (x right, y down, z forward), metres.
TILT = math.radians(30.0)  # the table plane's normal is 30 degrees off the viewing axis
PLANE_POINT = np.array([0.0, 0.0, 0.95])
PLANE_NORMAL = np.array([0.0, -math.sin(TILT), -math.cos(TILT)])  # towards the camera
BOX_LO, BOX_HI = np.array([-0.10, -0.07, 0.70]), np.array([0.06, 0.06, 0.80])  # in front of the plane
BOX_RGB, TABLE_RGB = (220, 40, 30), (110, 120, 130)


def _pixel_rays(intr: dict) -> np.ndarray:
    """(H, W, 3) rays with z = 1 through each pixel centre (librealsense puts them at integers)."""
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    return np.stack([(u - intr["ppx"]) / intr["fx"], (v - intr["ppy"]) / intr["fy"], np.ones_like(u)], axis=-1)


def _ray_cast(origin: np.ndarray, rays: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For rays from ``origin``: (distance to the first hit in units of the ray, hit on the box,
    unit normal of the surface hit)."""
    t_plane = ((PLANE_POINT - origin) @ PLANE_NORMAL) / (rays @ PLANE_NORMAL)
    with np.errstate(divide="ignore", invalid="ignore"):  # slab test; rays parallel to a slab give inf / nan
        t1, t2 = (BOX_LO - origin) / rays, (BOX_HI - origin) / rays
    entry = np.minimum(t1, t2)
    t_near = np.nanmax(entry, axis=-1)
    t_far = np.nanmin(np.maximum(t1, t2), axis=-1)
    on_box = (t_near <= t_far) & (t_near > 0)
    normal = np.where(on_box[..., None], np.eye(3)[np.nanargmax(entry, axis=-1)], PLANE_NORMAL)
    return np.where(on_box, t_near, t_plane), on_box, normal


def _scene_frames():
    """The depth image (mm, in the depth module's frame) and the colour image of the scene."""
    rays = _pixel_rays(DEPTH_INTR) @ T_COLOR_DEPTH[:3, :3].T  # depth-frame rays with z = 1, in the colour frame
    t, _, _ = _ray_cast(T_COLOR_DEPTH[:3, 3], rays)  # so the distance along them is the depth module's z
    assert np.isfinite(t).all() and t.max() < 1.5
    depth = np.round(t * 1000).astype(np.uint16)  # depth units 1 mm
    _, on_box, _ = _ray_cast(np.zeros(3), _pixel_rays(COLOR_INTR))
    color = np.where(on_box[..., None], BOX_RGB, TABLE_RGB).astype(np.uint8)
    return depth, color


def _expected(points: np.ndarray):
    """Where each point should be, given the depth image: on its own colour ray, at the depth the
    depth module measured for the surface that ray meets. librealsense's align writes the depth
    module's z into the colour image unchanged (src/proc/align.cpp, ``align_z_to_other``), so
    that z, not the colour frame's, is the truth here: they differ by (R p + t)_z - p_z, about
    1 mm for this module's 0.3-0.4 deg and 0.3 mm. Returns (expected z, on the box, slope), slope
    = tan of the angle between ray and surface normal: how fast the depth changes sideways."""
    rays = points / points[:, 2:3]
    t, on_box, normal = _ray_cast(np.zeros(3), rays)
    T_depth_color = invert_pose(T_COLOR_DEPTH)
    z_depth = (rays * t[:, None]) @ T_depth_color[2, :3] + T_depth_color[2, 3]
    cos = np.abs(np.sum(rays * normal, axis=1)) / np.linalg.norm(rays, axis=1)
    return z_depth, on_box, np.tan(np.arccos(np.clip(cos, 0.0, 1.0)))


def _rig():
    """The software D455 showing the still scene in every frame."""
    depth, color = _scene_frames()
    return SoftwareRealSense(
        FRONT.serial, (W, H), FRONT.fps, DEPTH_INTR, COLOR_INTR, T_COLOR_DEPTH, lambda k: (depth, color)
    )


@pytest.mark.parametrize("options", [{}, {"decimation": 1, "spatial": False, "temporal": False}], ids=["lab", "raw"])
def test_software_device_frames_become_a_cloud_on_the_scene(options):
    rig = _rig()
    cam = make_camera("realsense", replace(FRONT, options={**FRONT.options, **options}), device_source=rig)
    assert isinstance(cam, RealSenseCamera)
    cam.connect()
    try:
        # lab.yaml's settings reached the (software) sensors through the real library
        rs = rig.rs
        assert rig.color_sensor.get_option(rs.option.exposure) == 85.0  # 8500 us in the sensor's 100 us units
        assert rig.color_sensor.get_option(rs.option.white_balance) == 4600.0
        assert rig.color_sensor.get_option(rs.option.enable_auto_exposure) == 0.0
        assert rig.color_sensor.get_option(rs.option.enable_auto_white_balance) == 0.0
        for sensor in (rig.depth_sensor, rig.color_sensor):
            assert sensor.get_option(rs.option.global_time_enabled) == 1.0
        frames = [cam.read() for _ in range(4)]  # the temporal filter sees a history
    finally:
        cam.disconnect()

    decimation = cam.options.decimation
    for frame in frames:
        # stamped with the frameset's global-time timestamp (ms with us resolution)
        assert frame.stamp_ns in {round(rig.stamp_ms(k) * 1e3) * 1000 for k in range(rig.sent)}
        points, colors = frame.points, frame.colors
        assert points.dtype == np.float32 and colors.dtype == np.uint8
        # almost every colour pixel gets a depth: the depth module sees more than the colour one;
        # what it cannot see from 59 mm to the side (the box's shadow on the table) has none
        assert len(points) > 0.85 * (W // decimation) * (H // decimation), len(points)
        # sideways, each point is on the ray of the colour pixel it came from: projected into the
        # colour image it lands on a pixel centre of the decimated grid (librealsense scales the
        # intrinsics by 1/decimation, so decimated pixel i is full-resolution pixel i x decimation)
        p64 = points.astype(np.float64)
        u = COLOR_INTR["fx"] * p64[:, 0] / p64[:, 2] + COLOR_INTR["ppx"]
        v = COLOR_INTR["fy"] * p64[:, 1] / p64[:, 2] + COLOR_INTR["ppy"]
        for pixel in (u / decimation, v / decimation):
            assert np.abs(pixel - np.round(pixel)).max() < 1e-3
        assert u.min() > -0.5 and u.max() < W - 0.5 and v.min() > -0.5 and v.max() < H - 0.5
        z_expected, on_box, slope = _expected(p64)
        error = np.abs(points[:, 2] - z_expected)
        # Tolerance: 0.5 mm for the depth's 1 mm units, plus a sideways slip along the surface's
        # slope. Align gives each colour pixel the depth of a depth pixel whose footprint covers
        # it (up to ~1 depth pixel away); decimation takes the median of a 2x2 block and librealsense
        # scales the principal point as if that block's centre were its first pixel (half a pixel
        # more). So 1.5 depth pixels of slip, 1.5 per decimation step: error = slip x z/f x slope.
        slip_px = 1.5 * decimation
        tolerance = 0.0005 + slip_px * z_expected / DEPTH_INTR["fx"] * slope
        assert np.mean(error <= tolerance) > 0.99, np.percentile(error / tolerance, [50, 99, 99.9])
        # flying pixels: where decimation or the filters mix the box and the table behind it
        assert np.mean(error > 0.05) < 0.005, np.mean(error > 0.05)
        assert np.median(error) < 0.002, np.median(error)
        # the colour is that of the surface the point lies on (the colour image, aligned)
        red = np.all(colors == BOX_RGB, axis=1)
        assert on_box.sum() > 0.03 * len(points) and (~on_box).sum() > 0.5 * len(points)  # the box: ~4 %
        assert np.mean(red == on_box) > 0.99, np.mean(red == on_box)
        # and the box face's points cover its outline as the colour module sees it (within ~1.5
        # decimated pixels: 3.4 mm at 0.7 m)
        face = points[on_box & (np.abs(points[:, 2] - BOX_LO[2]) < 0.003)]
        np.testing.assert_allclose(face[:, 0].min(), BOX_LO[0], atol=0.004)
        np.testing.assert_allclose(face[:, 0].max(), BOX_HI[0], atol=0.004)
        np.testing.assert_allclose(face[:, 1].min(), BOX_LO[1], atol=0.004)
        np.testing.assert_allclose(face[:, 1].max(), BOX_HI[1], atol=0.004)
