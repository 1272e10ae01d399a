"""pyrealsense2 driver: one device by serial, depth aligned to colour, the usual filters, a coloured cloud.

Per frame: wait for a depth + colour frameset, align depth to the colour camera (so each
depth pixel has a colour and the cloud lives in ``<name>_color_optical_frame``, the frame
whose extrinsics lab.yaml holds), then decimation -> depth-to-disparity -> spatial ->
temporal -> disparity-to-depth -> hole filling (librealsense's recommended order), and
deproject with a per-pixel ray table built once from the stream intrinsics (exact for the
distortion model too, and a multiply per frame instead of a deprojection).

Stamps: with ``global_time_enabled`` the frame timestamp is the capture time on the host
clock (what the ROS clock is on hardware); otherwise the arrival time is used.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from ...config import CameraConfig, ConfigError, from_dict
from ...sync import PublishPacer
from ..base import Camera, CameraError, CloudFrame
from .config import RealSenseOptions


def pixel_rays(width: int, height: int, fx: float, fy: float, ppx: float, ppy: float,
               deproject: Callable[[float, float], tuple[float, float]] | None = None) -> np.ndarray:
    """(H, W, 2) float32: x/z and y/z of each pixel centre's viewing ray (optical frame).

    Pixel (u, v) covers [u, u+1) x [v, v+1) in librealsense's convention, whose principal
    point is given in the same continuous coordinates, so the ray through pixel (u, v)
    uses u itself (librealsense deprojects integer pixel coordinates). ``deproject(u, v)``
    (e.g. ``rs2_deproject_pixel_to_point`` at depth 1) handles lens distortion when given.
    """
    if deproject is None:
        u = (np.arange(width, dtype=np.float64) - ppx) / fx
        v = (np.arange(height, dtype=np.float64) - ppy) / fy
        rays = np.empty((height, width, 2), np.float32)
        rays[..., 0] = u[None, :]
        rays[..., 1] = v[:, None]
        return rays
    rays = np.empty((height, width, 2), np.float32)
    for v in range(height):
        for u in range(width):
            rays[v, u] = deproject(u, v)
    return rays


def depth_to_cloud(depth: np.ndarray, depth_scale: float, color: np.ndarray, rays: np.ndarray,
                   min_depth: float, max_depth: float) -> tuple[np.ndarray, np.ndarray]:
    """Depth image (H, W) uint16 + colour (H, W, 3) uint8 aligned to it -> points, colours.

    Zero depth (no measurement) and depths outside [min_depth, max_depth] are dropped.
    """
    if depth.shape != color.shape[:2] or depth.shape != rays.shape[:2]:
        raise CameraError(f"depth {depth.shape}, colour {color.shape} and rays {rays.shape} disagree")
    z = depth.astype(np.float32) * np.float32(depth_scale)
    valid = (depth > 0) & (z >= min_depth) & (z <= max_depth)
    zv = z[valid]
    points = np.empty((len(zv), 3), np.float32)
    points[:, 0] = rays[..., 0][valid] * zv
    points[:, 1] = rays[..., 1][valid] * zv
    points[:, 2] = zv
    return points, np.ascontiguousarray(color[valid])


class RealSenseCamera(Camera):
    """One RealSense device, selected by ``camera.serial``; options from ``camera.options``."""

    def __init__(self, camera: CameraConfig, clock: Callable[[], int] = time.time_ns, pace_hz: float | None = None,
                 **overrides):
        try:
            self.options = from_dict(RealSenseOptions, {**camera.options, **overrides},
                                     where=f"cameras[{camera.name}].options")
        except ConfigError as err:
            raise CameraError(str(err)) from err
        self.camera = camera
        self._clock = clock
        # Process (align, filter, deproject) only the frames that will be published: at 30 fps
        # in and 5 Hz out, the others are fetched from the device and dropped unprocessed.
        self._pacer = PublishPacer(pace_hz) if pace_hz else None
        self._pipeline = None
        self._align = None
        self._filters: list = []
        self._depth_scale = 0.0
        self._rays: dict[tuple, np.ndarray] = {}

    @property
    def is_connected(self) -> bool:
        return self._pipeline is not None

    def connect(self) -> None:
        if self._pipeline is not None:
            return
        try:
            import pyrealsense2 as rs
        except ImportError as err:
            raise CameraError(f"RealSense camera {self.camera.name!r}: pyrealsense2 is not installed "
                              f"(pip install pyrealsense2): {err}") from err
        cam, opt = self.camera, self.options
        ctx = rs.context()
        found = [d.get_info(rs.camera_info.serial_number) for d in ctx.query_devices()]
        if cam.serial not in found:
            raise CameraError(f"RealSense camera {cam.name!r} with serial {cam.serial} not found; "
                              f"connected RealSense serials: {found or 'none'}")
        cfg = rs.config()
        cfg.enable_device(cam.serial)
        cfg.enable_stream(rs.stream.depth, opt.depth_width or cam.width, opt.depth_height or cam.height,
                          rs.format.z16, cam.fps)
        cfg.enable_stream(rs.stream.color, cam.width, cam.height, rs.format.rgb8, cam.fps)
        pipeline = rs.pipeline(ctx)
        try:
            profile = pipeline.start(cfg)
        except RuntimeError as err:
            raise CameraError(f"RealSense camera {cam.name!r} ({cam.serial}): cannot start "
                              f"{cam.width}x{cam.height}@{cam.fps}: {err}") from err
        try:
            device = profile.get_device()
            depth_sensor = device.first_depth_sensor()
            color_sensor = device.first_color_sensor()
            self._depth_scale = depth_sensor.get_depth_scale()
            self._configure_sensors(rs, depth_sensor, color_sensor)
        except (RuntimeError, CameraError) as err:
            pipeline.stop()
            raise CameraError(f"RealSense camera {cam.name!r} ({cam.serial}): {err}") from err
        self._align = rs.align(rs.stream.color)
        self._filters = self._make_filters(rs)
        self._rs = rs
        self._pipeline = pipeline

    def _configure_sensors(self, rs, depth_sensor, color_sensor) -> None:
        opt = self.options

        def set_option(sensor, option, value, what):
            if not sensor.supports(option):
                raise CameraError(f"{what} is not supported by this device")
            sensor.set_option(option, float(value))

        for sensor in (depth_sensor, color_sensor):
            if sensor.supports(rs.option.global_time_enabled):
                sensor.set_option(rs.option.global_time_enabled, 1.0)
        if opt.visual_preset is not None:
            preset = getattr(rs.rs400_visual_preset, opt.visual_preset)
            set_option(depth_sensor, rs.option.visual_preset, int(preset), "visual_preset")
        if opt.laser_power is not None:
            set_option(depth_sensor, rs.option.laser_power, opt.laser_power, "laser_power")
        if opt.depth_exposure_us is not None:
            set_option(depth_sensor, rs.option.enable_auto_exposure, 0, "depth auto exposure")
            set_option(depth_sensor, rs.option.exposure, opt.depth_exposure_us, "depth_exposure_us")
        if opt.exposure_us is not None:
            set_option(color_sensor, rs.option.enable_auto_exposure, 0, "colour auto exposure")
            # the colour sensor's exposure option is in units of 100 us
            set_option(color_sensor, rs.option.exposure, opt.exposure_us / 100.0, "exposure_us")
        if opt.white_balance_k is not None:
            set_option(color_sensor, rs.option.enable_auto_white_balance, 0, "auto white balance")
            set_option(color_sensor, rs.option.white_balance, opt.white_balance_k, "white_balance_k")

    def _make_filters(self, rs) -> list:
        opt = self.options
        filters = []
        if opt.decimation > 1:
            dec = rs.decimation_filter()
            dec.set_option(rs.option.filter_magnitude, opt.decimation)
            filters.append(dec)
        if opt.spatial or opt.temporal:
            filters.append(rs.disparity_transform(True))
            if opt.spatial:
                filters.append(rs.spatial_filter())
            if opt.temporal:
                filters.append(rs.temporal_filter())
            filters.append(rs.disparity_transform(False))
        if opt.hole_filling:
            filters.append(rs.hole_filling_filter())
        return filters

    def read(self, timeout_s: float = 1.0) -> CloudFrame:
        if self._pipeline is None:
            raise CameraError(f"RealSense camera {self.camera.name!r} is not connected")
        rs = self._rs
        deadline = time.monotonic() + timeout_s
        while True:
            left_ms = int((deadline - time.monotonic()) * 1000)
            try:
                if left_ms < 1:
                    raise RuntimeError("timeout")
                frames = self._pipeline.wait_for_frames(left_ms)
            except RuntimeError as err:
                raise CameraError(f"RealSense camera {self.camera.name!r} ({self.camera.serial}): "
                                  f"no frame within {timeout_s} s: {err}") from err
            if self._pacer is None or self._pacer.due(time.time()):
                break
        arrival_ns = self._clock()
        aligned = self._align.process(frames)
        depth_frame = aligned.get_depth_frame()
        color_frame = aligned.get_color_frame()
        if not depth_frame or not color_frame:
            raise CameraError(f"RealSense camera {self.camera.name!r}: incomplete frameset")
        for f in self._filters:
            depth_frame = f.process(depth_frame)
        depth = np.asanyarray(depth_frame.get_data())
        color = np.asanyarray(color_frame.get_data())
        if depth.shape != color.shape[:2]:  # decimated: sample the colour at each depth pixel's centre
            sy, sx = color.shape[0] // depth.shape[0], color.shape[1] // depth.shape[1]
            color = color[sy // 2::sy, sx // 2::sx][: depth.shape[0], : depth.shape[1]]
        intr = depth_frame.profile.as_video_stream_profile().get_intrinsics()
        points, colors = depth_to_cloud(depth, self._depth_scale, color, self._rays_for(intr),
                                        self.camera.min_depth, self.camera.max_depth)
        if frames.get_frame_timestamp_domain() == rs.timestamp_domain.global_time:
            stamp_ns = round(frames.get_timestamp() * 1e3) * 1000  # ms with us resolution -> ns
        else:
            stamp_ns = arrival_ns
        return CloudFrame(points, colors, stamp_ns)

    def _rays_for(self, intr) -> np.ndarray:
        key = (intr.width, intr.height, intr.fx, intr.fy, intr.ppx, intr.ppy, tuple(intr.coeffs))
        if key not in self._rays:
            rs = self._rs
            distorted = any(abs(c) > 0 for c in intr.coeffs) and intr.model != rs.distortion.none

            def deproject(u, v):
                x, y, _ = rs.rs2_deproject_pixel_to_point(intr, [float(u), float(v)], 1.0)
                return x, y

            self._rays[key] = pixel_rays(intr.width, intr.height, intr.fx, intr.fy, intr.ppx, intr.ppy,
                                         deproject if distorted else None)
        return self._rays[key]

    def disconnect(self) -> None:
        if self._pipeline is not None:
            try:
                self._pipeline.stop()
            except RuntimeError:
                pass  # already stopped (device unplugged)
            self._pipeline = None
