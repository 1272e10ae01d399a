"""pyrealsense2 driver: one device by serial, depth aligned to colour, the usual filters, a coloured cloud.

Per frame: wait for a depth + colour frameset, align depth to the colour camera (so each
depth pixel has a colour and the cloud lives in ``<name>_color_optical_frame``, the frame
whose extrinsics lab.yaml holds), then decimation -> depth-to-disparity -> spatial ->
temporal -> disparity-to-depth -> hole filling (librealsense's recommended order), and
deproject with a per-pixel ray table built once from the stream intrinsics (exact for the
distortion model too, and a multiply per frame instead of a deprojection).

The frame also carries the full-resolution colour image (rgb8), before any decimation.

Stamps: with ``global_time_enabled`` the frame timestamp is the capture time on the host
clock (what the ROS clock is on hardware); otherwise the arrival time is used.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ...config import CameraConfig, ConfigError, from_dict
from ...perception.sync import PublishPacer
from ..base import Camera, CameraError, CameraHealth, CloudFrame
from .config import RealSenseOptions
from .devices import connected_devices, device_info, find_device, usb2_warning


def pixel_rays(
    width: int,
    height: int,
    fx: float,
    fy: float,
    ppx: float,
    ppy: float,
    deproject: Callable[[float, float], tuple[float, float]] | None = None,
) -> np.ndarray:
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


def depth_to_cloud(
    depth: np.ndarray, depth_scale: float, color: np.ndarray, rays: np.ndarray, min_depth: float, max_depth: float
) -> tuple[np.ndarray, np.ndarray]:
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


# While a camera recovers, read() looks for its serial on the bus this often.
_POLL_S = 0.2
# After hardware_reset() a D4xx drops off the bus and re-enumerates a few seconds later. A
# serial still listed this long after the reset has reset already (or ignored it): open it.
_RESET_SETTLE_S = 2.0


@dataclass
class _Recovery:
    """Between a stall and the stream's return (see ``RealSenseCamera.read``)."""

    reset_at: float  # monotonic time of the latest reset (or of finding the device gone)
    give_up_at: float  # reset_at + reenumerate_timeout_s: this attempt has failed after it
    note: str  # what the latest attempt did: "hardware reset", "not on the bus (unplugged?)", ...
    gone_seen: bool = False  # the serial has left the bus since the reset
    retry_at: float | None = None  # after a failed attempt: the next reset is due then
    last_error: str = ""  # why the latest re-open failed, if it did


class RealSenseCamera(Camera):
    """One RealSense device, selected by ``camera.serial``; options from ``camera.options``.

    Recovery: ``options.reset_after_timeouts`` read timeouts in a row stop the pipeline and
    hardware-reset the device; later reads wait (each at most about ``timeout_s``) for the
    serial to re-enumerate, then open it again exactly as ``connect`` does (streams, sensor
    options, filters, alignment), and return frames once it streams. An attempt that does not
    bring the device back within ``reenumerate_timeout_s`` is retried with a doubling back-off;
    until then every read raises a CameraError saying which state the camera is in.
    ``monotonic`` and ``sleep`` time the recovery (tests pass a fake clock).

    ``device_source`` is where the ``context()`` and ``pipeline(context)`` come from: None means
    pyrealsense2 itself (a device on USB); a test passes librealsense ``software_device`` frames
    through it (test/helpers_realsense.py), and everything else (streams, options, alignment,
    filters, deprojection) is this same code on the real library.
    """

    def __init__(
        self,
        camera: CameraConfig,
        clock: Callable[[], int] = time.time_ns,
        pace_hz: float | None = None,
        monotonic: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
        device_source=None,
        **overrides,
    ):
        try:
            self.options = from_dict(
                RealSenseOptions, {**camera.options, **overrides}, where=f"cameras[{camera.name}].options"
            )
        except ConfigError as err:
            raise CameraError(str(err)) from err
        self.camera = camera
        self._clock = clock
        self._monotonic, self._sleep = monotonic, sleep
        self._device_source = device_source
        # Process (align, filter, deproject) only the frames that will be published: at 30 fps
        # in and 5 Hz out, the others are fetched from the device and dropped unprocessed.
        self._pacer = PublishPacer(pace_hz) if pace_hz else None
        self._rs = None
        self._ctx = None
        self._opened = False  # connect() succeeded and disconnect() has not been called
        self._pipeline = None
        self._align = None
        self._filters: list = []
        self._depth_scale = 0.0
        self._rays: dict[tuple, np.ndarray] = {}
        self._timeouts = 0  # frame timeouts in a row
        self._recoveries_without_frame = 0  # recoveries begun since the last frame
        self._recovery: _Recovery | None = None
        self._resets = 0
        self._reconnects = 0
        self._last_reason = ""

    @property
    def is_connected(self) -> bool:
        return self._pipeline is not None

    def health(self) -> CameraHealth:
        return CameraHealth(
            resets=self._resets,
            reconnects=self._reconnects,
            recovering=self._recovery is not None,
            last_recovery_reason=self._last_reason,
        )

    def _where(self) -> str:
        return f"RealSense camera {self.camera.name!r} ({self.camera.serial})"

    def connect(self) -> None:
        if self._opened:
            return
        try:
            import pyrealsense2 as rs
        except ImportError as err:
            raise CameraError(
                f"RealSense camera {self.camera.name!r}: pyrealsense2 is not installed "
                f"(pip install pyrealsense2): {err}"
            ) from err
        cam = self.camera
        self._rs, self._ctx = rs, (self._device_source or rs).context()
        found = self._connected_serials()
        if cam.serial not in found:
            raise CameraError(
                f"RealSense camera {cam.name!r} with serial {cam.serial} not found; "
                f"connected RealSense serials: {found or 'none'}"
            )
        self._open()
        self._opened = True

    def _connected_serials(self) -> list[str]:
        try:
            return [info.serial for info, _ in connected_devices(self._rs, self._ctx)]
        except RuntimeError:  # a device dropped off the bus while it was being queried
            return []

    def _device(self):
        try:
            return find_device(self._rs, self._ctx, self.camera.serial)
        except RuntimeError:
            return None

    def _open(self) -> None:
        """Start the streams and apply every option: the first connect and each reconnect."""
        rs, cam, opt = self._rs, self.camera, self.options
        cfg = rs.config()
        cfg.enable_device(cam.serial)
        cfg.enable_stream(
            rs.stream.depth, opt.depth_width or cam.width, opt.depth_height or cam.height, rs.format.z16, cam.fps
        )
        cfg.enable_stream(rs.stream.color, cam.width, cam.height, rs.format.rgb8, cam.fps)
        pipeline = (self._device_source or rs).pipeline(self._ctx)
        try:
            profile = pipeline.start(cfg)
        except RuntimeError as err:
            device = self._device()
            usb2 = device is not None and usb2_warning(device_info(rs, device), f"{cam.width}x{cam.height}@{cam.fps}")
            raise CameraError(
                f"{self._where()}: cannot start {cam.width}x{cam.height}@{cam.fps}: {err}"
                + (f"; {usb2}" if usb2 else "")
            ) from err
        try:
            device = profile.get_device()
            depth_sensor = device.first_depth_sensor()
            color_sensor = device.first_color_sensor()
            self._depth_scale = depth_sensor.get_depth_scale()
            self._configure_sensors(rs, depth_sensor, color_sensor)
        except (RuntimeError, CameraError) as err:
            pipeline.stop()
            raise CameraError(f"{self._where()}: {err}") from err
        self._align = rs.align(rs.stream.color)
        self._filters = self._make_filters(rs)  # fresh: the temporal filter forgets frames from before a stall
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
        """The next frame; see the class docstring for what happens after timeouts."""
        if not self._opened:
            raise CameraError(f"RealSense camera {self.camera.name!r} is not connected")
        rs = self._rs
        deadline = self._monotonic() + timeout_s
        if self._recovery is not None:
            self._recover(deadline)  # returns once the stream is open again, else raises
            deadline = self._monotonic() + timeout_s  # the first frame after a reconnect gets a full timeout
        while True:
            left_ms = int((deadline - self._monotonic()) * 1000)
            try:
                if left_ms < 1:
                    raise RuntimeError("timeout")
                frames = self._pipeline.wait_for_frames(left_ms)
            except RuntimeError as err:
                raise self._timed_out(timeout_s, err) from err
            self._timeouts = 0
            self._recoveries_without_frame = 0
            if self._pacer is None or self._pacer.due(time.time()):
                break
        arrival_ns = self._clock()
        try:  # librealsense raises RuntimeError when the device goes away mid-frame
            aligned = self._align.process(frames)
            depth_frame = aligned.get_depth_frame()
            color_frame = aligned.get_color_frame()
            if not depth_frame or not color_frame:
                raise CameraError(f"RealSense camera {self.camera.name!r}: incomplete frameset")
            for f in self._filters:
                depth_frame = f.process(depth_frame)
            depth = np.asanyarray(depth_frame.get_data())
            # a copy: the frame's buffer goes back to librealsense once the frameset is released
            image = np.array(color_frame.get_data(), dtype=np.uint8, copy=True)
            color = image
        except RuntimeError as err:
            raise CameraError(f"{self._where()}: frame processing failed: {err}") from err
        if depth.shape != color.shape[:2]:  # decimated: sample the colour at each depth pixel's centre
            sy, sx = color.shape[0] // depth.shape[0], color.shape[1] // depth.shape[1]
            color = color[sy // 2 :: sy, sx // 2 :: sx][: depth.shape[0], : depth.shape[1]]
        intr = depth_frame.profile.as_video_stream_profile().get_intrinsics()
        points, colors = depth_to_cloud(
            depth, self._depth_scale, color, self._rays_for(intr), self.camera.min_depth, self.camera.max_depth
        )
        if frames.get_frame_timestamp_domain() == rs.timestamp_domain.global_time:
            stamp_ns = round(frames.get_timestamp() * 1e3) * 1000  # ms with us resolution -> ns
        else:
            stamp_ns = arrival_ns
        return CloudFrame(points, colors, stamp_ns, image)

    def _rays_for(self, intr) -> np.ndarray:
        key = (intr.width, intr.height, intr.fx, intr.fy, intr.ppx, intr.ppy, tuple(intr.coeffs))
        if key not in self._rays:
            rs = self._rs
            distorted = any(abs(c) > 0 for c in intr.coeffs) and intr.model != rs.distortion.none

            def deproject(u, v):
                x, y, _ = rs.rs2_deproject_pixel_to_point(intr, [float(u), float(v)], 1.0)
                return x, y

            self._rays[key] = pixel_rays(
                intr.width, intr.height, intr.fx, intr.fy, intr.ppx, intr.ppy, deproject if distorted else None
            )
        return self._rays[key]

    # --- recovery from a stalled or unplugged device -------------------------------------

    def _timed_out(self, timeout_s: float, err: Exception) -> CameraError:
        self._timeouts += 1
        message = f"{self._where()}: no frame within {timeout_s} s: {err}"
        if self._timeouts < self.options.reset_after_timeouts:
            return CameraError(message)
        count = self._timeouts
        self._begin_recovery(f"{count} frame timeouts in a row")
        rec = self._recovery
        if rec.retry_at is not None:
            then = f"the last reconnect brought no frame: next reset in {rec.retry_at - rec.reset_at:.1f} s"
        else:
            then = f"{rec.note}, waiting up to {self.options.reenumerate_timeout_s} s for it to come back"
        return CameraError(f"{message}; {count} in a row: stream stopped, {then}")

    def _begin_recovery(self, reason: str) -> None:
        self._last_reason = reason
        self._timeouts = 0
        self._recoveries_without_frame += 1
        self._close_pipeline()
        now = self._monotonic()
        self._recovery = _Recovery(reset_at=now, give_up_at=now, note="waiting to reset")
        if self._recoveries_without_frame > 1:  # the last reconnect brought no frame: back off first
            self._recovery.retry_at = now + self._backoff_s()
        else:
            self._reset(now)

    def _backoff_s(self) -> float:
        opt = self.options
        failed = max(self._recoveries_without_frame - 1, 1)
        return min(opt.reconnect_backoff_s * 2 ** (failed - 1), opt.reconnect_backoff_max_s)

    def _reset(self, now: float) -> None:
        rec = self._recovery
        device = self._device()
        rec.gone_seen = device is None
        if device is None:
            rec.note = "not on the bus (unplugged?)"
        else:
            try:
                device.hardware_reset()
                self._resets += 1
                rec.note = "hardware reset"
            except RuntimeError as err:
                rec.note = f"hardware reset failed ({err})"
        rec.reset_at, rec.give_up_at, rec.retry_at = now, now + self.options.reenumerate_timeout_s, None

    def _recover(self, deadline: float) -> None:
        rec, opt = self._recovery, self.options
        while True:
            now = self._monotonic()
            if rec.retry_at is not None:  # backing off after a failed attempt
                if now >= rec.retry_at:
                    self._reset(now)
                    continue
                if now >= deadline:
                    raise CameraError(
                        f"{self._where()} has not come back: no frame after {self._recoveries_without_frame - 1} "
                        f"recovery attempt(s) (it stalled: {self._last_reason}); next attempt in "
                        f"{rec.retry_at - now:.1f} s; connected RealSense serials: {self._connected_serials() or 'none'}"
                        + (f"; last error: {rec.last_error}" if rec.last_error else "")
                    )
                self._sleep(min(rec.retry_at, deadline) - now)
                continue
            if self._device() is None:
                rec.gone_seen = True
            elif rec.gone_seen or now - rec.reset_at >= _RESET_SETTLE_S:
                try:
                    self._open()
                except CameraError as err:
                    rec.last_error = str(err)  # still booting, or broken: retried until give_up_at
                else:
                    self._recovery = None
                    self._reconnects += 1
                    return
            if now >= rec.give_up_at:
                self._recoveries_without_frame += 1
                rec.retry_at = now + self._backoff_s()
                continue
            if now >= deadline:
                raise CameraError(
                    f"{self._where()}: recovering after {self._last_reason}: {rec.note}, "
                    f"waiting for the serial to re-enumerate ({now - rec.reset_at:.1f} s of "
                    f"{opt.reenumerate_timeout_s} s)" + (f"; last error: {rec.last_error}" if rec.last_error else "")
                )
            self._sleep(min(_POLL_S, deadline - now))

    def _close_pipeline(self) -> None:
        if self._pipeline is not None:
            try:
                self._pipeline.stop()
            except RuntimeError:
                pass  # already stopped (device unplugged)
            self._pipeline = None

    def disconnect(self) -> None:
        self._close_pipeline()
        self._recovery = None
        self._opened = False
