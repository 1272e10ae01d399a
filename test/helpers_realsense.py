"""A fake ``pyrealsense2`` module: the names RealSenseCamera and `equidiff cameras list` use, over scripted devices.

There is no RealSense here, so the hardware is faked at the library boundary: install it with
``monkeypatch.setitem(sys.modules, "pyrealsense2", bus.module)`` and the real driver code runs
against it. Time is a ``FakeClock``: a blocking wait advances it instead of sleeping, so the
recovery tests run in milliseconds and are not timed against the wall clock.

Behaviour modelled on librealsense: ``wait_for_frames`` raises ``RuntimeError`` after its timeout
while a device is stalled or gone; ``hardware_reset`` drops the device off the bus for
``reset_s`` and brings it back with its sensor options at their defaults; ``pipeline.start``
fails for a device that is not on the bus, and for 848x480 depth over a USB 2 link.
"""

from __future__ import annotations

import time
import types
from pathlib import Path
from types import SimpleNamespace as NS

import numpy as np

OPTIONS = (
    "global_time_enabled",
    "visual_preset",
    "laser_power",
    "enable_auto_exposure",
    "exposure",
    "enable_auto_white_balance",
    "white_balance",
    "filter_magnitude",
)


class FakeClock:
    def __init__(self):
        self.now = 0.0

    def monotonic(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.now += max(seconds, 0.0)


class WallClock:
    """The real clock, for a fake device driven by a node in another process (hang guards only)."""

    @property
    def now(self) -> float:
        return time.monotonic()

    def monotonic(self) -> float:
        return time.monotonic()

    def sleep(self, seconds: float) -> None:
        time.sleep(max(seconds, 0.0))


def install_in_subprocess(directory, serials, stall_after_frames=None, reset_s=1.0) -> str:
    """Write a ``pyrealsense2`` package into ``directory`` that is this fake on the wall clock; return
    the directory to put first on PYTHONPATH. Each device in ``serials`` stalls after
    ``stall_after_frames`` frames (None: never) until it is hardware-reset."""
    package = Path(directory) / "pyrealsense2"
    package.mkdir(parents=True, exist_ok=True)
    (package / "__init__.py").write_text(f"""\
import sys
sys.path.insert(0, {str(Path(__file__).parent)!r})
import numpy as np
from helpers_realsense import FakeRealSense, WallClock

bus = FakeRealSense(WallClock(), np.full((6, 8), 800, np.uint16), np.full((6, 8, 3), 7, np.uint8), reset_s={reset_s!r})
for serial in {list(serials)!r}:
    bus.plug(serial).stall_after_frames = {stall_after_frames!r}
sys.modules[__name__] = bus.module
""")
    return str(directory)


class FakeSensor:
    def __init__(self, depth_scale=0.001):
        self.values: dict[str, float] = {}  # the option values now in effect
        self.set_calls: list[tuple[str, float]] = []  # every set_option ever made
        self.depth_scale = depth_scale

    def supports(self, option) -> bool:
        return option in OPTIONS

    def set_option(self, option, value) -> None:
        self.values[option] = value
        self.set_calls.append((option, value))

    def get_depth_scale(self) -> float:
        return self.depth_scale


class FakeDevice:
    def __init__(self, bus, serial, name="Intel RealSense D455", firmware="5.16.0.1", usb_type="3.2"):
        self.bus = bus
        self.info = {
            "serial_number": serial,
            "name": name,
            "firmware_version": firmware,
            "usb_type_descriptor": usb_type,
        }
        self.depth_sensor, self.color_sensor = FakeSensor(), FakeSensor()
        self.plugged = True
        self.stalled = False  # streams started on it deliver no frames
        self.fixed_by_reset = True  # a hardware reset clears a stall
        self.back_at = 0.0  # after a reset: off the bus until this time
        self.resets = 0
        self.stall_after_frames: int | None = None  # stall by itself after this many frames (once)
        self.frames = 0

    @property
    def serial(self) -> str:
        return self.info["serial_number"]

    @property
    def on_bus(self) -> bool:
        return self.plugged and self.bus.clock.now >= self.back_at

    def supports(self, info) -> bool:
        return info in self.info

    def get_info(self, info) -> str:
        if not self.on_bus:
            raise RuntimeError("No device connected")
        return self.info[info]

    def hardware_reset(self) -> None:
        if not self.on_bus:
            raise RuntimeError("No device connected")
        self.resets += 1
        self.back_at = self.bus.clock.now + self.bus.reset_s
        for sensor in (self.depth_sensor, self.color_sensor):
            sensor.values.clear()  # a reset restores the defaults
        if self.fixed_by_reset:
            self.stalled = False

    def first_depth_sensor(self):
        return self.depth_sensor

    def first_color_sensor(self):
        return self.color_sensor

    def applied(self) -> dict:
        return {"depth": dict(self.depth_sensor.values), "color": dict(self.color_sensor.values)}


class FakeFilter:
    def __init__(self, kind):
        self.kind, self.values = kind, {}

    def set_option(self, option, value):
        self.values[option] = value

    def process(self, frame):
        return frame


class FakeRealSense:
    """The bus and the fake module. ``plug(serial, ...)`` connects a device."""

    def __init__(self, clock: FakeClock, depth: np.ndarray, color: np.ndarray, reset_s=3.0, fps=30.0):
        self.clock, self.depth, self.color, self.reset_s, self.fps = clock, depth, color, reset_s, fps
        self.devices: list[FakeDevice] = []
        self.starts: list[str] = []  # serial of each successful pipeline.start
        self.filters: list[FakeFilter] = []
        self.module = self._module()

    def plug(self, serial, **info) -> FakeDevice:
        device = FakeDevice(self, serial, **info)
        self.devices.append(device)
        return device

    def _on_bus(self, serial):
        return next((d for d in self.devices if d.serial == serial and d.on_bus), None)

    def _frameset(self):
        h, w = self.depth.shape
        intr = NS(width=w, height=h, fx=4.0, fy=4.0, ppx=w / 2, ppy=h / 2, coeffs=[0.0] * 5, model="none")

        def frame(data):
            return NS(
                get_data=lambda: data, profile=NS(as_video_stream_profile=lambda: NS(get_intrinsics=lambda: intr))
            )

        depth, color = frame(self.depth), frame(self.color)
        stamp_ms = self.clock.now * 1e3
        return NS(
            get_depth_frame=lambda: depth,
            get_color_frame=lambda: color,
            get_timestamp=lambda: stamp_ms,
            get_frame_timestamp_domain=lambda: "global",
        )

    def _module(self):
        bus = self

        class context:
            def query_devices(self):
                return [d for d in bus.devices if d.on_bus]

        class config:
            def __init__(self):
                self.serial, self.streams = None, []

            def enable_device(self, serial):
                self.serial = serial

            def enable_stream(self, stream, width, height, fmt, fps):
                self.streams.append((stream, width, height, fmt, fps))

        class pipeline:
            def __init__(self, ctx):
                self.device = None

            def start(self, cfg):
                device = bus._on_bus(cfg.serial)
                if device is None:
                    raise RuntimeError("No device connected")
                if device.info["usb_type_descriptor"].startswith("2") and any(
                    s[0] == "depth" and s[1] >= 848 for s in cfg.streams
                ):
                    raise RuntimeError("Couldn't resolve requests")
                self.device = device
                bus.starts.append(device.serial)
                return NS(get_device=lambda: device)

            def wait_for_frames(self, timeout_ms):
                device = self.device
                if device is None or not device.on_bus or device.stalled:
                    bus.clock.sleep(timeout_ms / 1000)
                    raise RuntimeError(f"Frame didn't arrive within {timeout_ms}")
                bus.clock.sleep(1.0 / bus.fps)
                device.frames += 1
                if device.frames == device.stall_after_frames:
                    device.stalled = True
                return bus._frameset()

            def stop(self):
                if self.device is None:
                    raise RuntimeError("stop() cannot be called before start()")
                self.device = None

        def make_filter(kind):
            def build(*args):
                f = FakeFilter(kind)
                bus.filters.append(f)
                return f

            return build

        module = types.ModuleType("pyrealsense2")
        module.context, module.config, module.pipeline = context, config, pipeline
        module.camera_info = NS(
            serial_number="serial_number",
            name="name",
            firmware_version="firmware_version",
            usb_type_descriptor="usb_type_descriptor",
        )
        module.option = NS(**{name: name for name in OPTIONS})
        module.rs400_visual_preset = NS(custom=0, default=1, hand=2, high_accuracy=3, high_density=4, medium_density=5)
        module.stream = NS(depth="depth", color="color")
        module.format = NS(z16="z16", rgb8="rgb8")
        module.timestamp_domain = NS(global_time="global", system_time="system")
        module.distortion = NS(none="none")
        module.align = lambda stream: NS(process=lambda frames: frames)
        for kind in (
            "decimation_filter",
            "disparity_transform",
            "spatial_filter",
            "temporal_filter",
            "hole_filling_filter",
        ):
            setattr(module, kind, make_filter(kind))
        return module


class SoftwareRealSense:
    """A RealSense made of librealsense's own ``software_device``: the real library, frames we make.

    Pass it as ``RealSenseCamera(..., device_source=rig)``: the backend's context lists this
    device, and its pipeline delivers the depth and colour frames that ``frames(k)`` returns
    (uint16 depth in ``depth_units``, RGB) as real librealsense frames, stamped in the global
    time domain at ``t0_ms + k / fps``. Everything after that is the backend's code on the real
    library: stream and sensor options (software sensors carry the D455's option set),
    ``rs.align`` with the depth-to-colour extrinsics registered here, the filters, the
    deprojection.

    Two pieces stand in for what a software_device cannot do in pyrealsense2 2.59:

    * ``rs.pipeline`` cannot open it: ``software_device.add_to(context)`` registers a device-info
      that the context holds only weakly and that nothing else holds, so ``query_devices`` never
      lists it (librealsense src/rs.cpp, ``rs2_context_add_software_device``). The pipeline here
      opens the two sensors into an ``rs.syncer``, as a pipeline does, and pushes one frame per
      stream on each ``wait_for_frames``.
    * A software sensor can become a depth sensor (given ``depth_units``) but never a colour
      sensor, so ``first_color_sensor`` is answered with the sensor that streams colour.

    What stays with ``FakeRealSense`` above: devices leaving and rejoining the bus,
    ``hardware_reset``, stalls and timeouts on a fake clock, USB link types.
    """

    def __init__(
        self,
        serial: str,
        size: tuple[int, int],
        fps: int,
        depth_intrinsics: dict,
        color_intrinsics: dict,
        T_color_depth: np.ndarray,
        frames,
        depth_units: float = 0.001,
        t0_ms: float = 1.7e12,
    ):
        import pyrealsense2 as rs

        self.rs, self.size, self.fps, self.frames_of = rs, size, fps, frames
        self.depth_units, self.t0_ms = depth_units, t0_ms
        self.sent = 0  # frame pairs pushed into the library
        device = rs.software_device()
        for key, value in {
            "serial_number": serial,
            "name": "Intel RealSense D455 (software_device)",
            "firmware_version": "5.16.0.1",
            "usb_type_descriptor": "3.2",
        }.items():
            device.register_info(getattr(rs.camera_info, key), value)
        self.depth_sensor = device.add_sensor("Stereo Module")
        self.color_sensor = device.add_sensor("RGB Camera")
        self.depth_profile = self._add_stream(self.depth_sensor, rs.stream.depth, rs.format.z16, 2, depth_intrinsics, 0)
        self.color_profile = self._add_stream(
            self.color_sensor, rs.stream.color, rs.format.rgb8, 3, color_intrinsics, 1
        )
        extrinsics = rs.extrinsics()
        extrinsics.rotation = [float(v) for v in T_color_depth[:3, :3].T.ravel()]  # librealsense: column-major
        extrinsics.translation = [float(v) for v in T_color_depth[:3, 3]]
        self.depth_profile.register_extrinsics_to(self.color_profile, extrinsics)
        # depth units make it a depth sensor; a stereo baseline (mm, a D455's) a stereo one, without
        # which the disparity transform passes depth through and the spatial filter smooths depth
        self.depth_sensor.add_read_only_option(rs.option.depth_units, depth_units)
        self.depth_sensor.add_read_only_option(rs.option.stereo_baseline, 95.0)
        # the options a D455 has and RealSenseCamera sets (ranges wide enough for lab.yaml's values)
        for sensor, options in (
            (
                self.depth_sensor,
                ("global_time_enabled", "visual_preset", "laser_power", "enable_auto_exposure", "exposure"),
            ),
            (
                self.color_sensor,
                (
                    "global_time_enabled",
                    "enable_auto_exposure",
                    "exposure",
                    "enable_auto_white_balance",
                    "white_balance",
                ),
            ),
        ):
            for name in options:
                sensor.add_option(getattr(rs.option, name), rs.option_range(0, 200000, 1, 1), True)
        device.create_matcher(rs.matchers.default)
        self.device = device
        self.handle = _SoftwareDeviceHandle(device, self.color_sensor)
        self._keep: list = []  # the numpy buffers of the frames in flight

    def _add_stream(self, sensor, stream, fmt, bpp, intrinsics, uid):
        rs = self.rs
        intr = rs.intrinsics()
        intr.width, intr.height = self.size
        intr.fx, intr.fy, intr.ppx, intr.ppy = (intrinsics[k] for k in ("fx", "fy", "ppx", "ppy"))
        intr.model, intr.coeffs = rs.distortion.brown_conrady, [0.0] * 5
        video = rs.video_stream()
        video.type, video.index, video.uid = stream, 0, uid
        video.width, video.height, video.fps, video.bpp, video.fmt = *self.size, self.fps, bpp, fmt
        video.intrinsics = intr
        return sensor.add_video_stream(video, True)

    # --- what RealSenseCamera asks of ``device_source`` -------------------------------------
    def context(self):
        return NS(query_devices=lambda: [self.handle])

    def pipeline(self, ctx):
        return _SoftwarePipeline(self)

    # --- frames -------------------------------------------------------------------------
    def stamp_ms(self, k: int) -> float:
        return self.t0_ms + k * 1000.0 / self.fps

    def push(self) -> None:
        """The device's next frame pair, into the library."""
        rs, k = self.rs, self.sent
        depth, color = self.frames_of(k)
        w, h = self.size
        assert depth.shape == (h, w) and depth.dtype == np.uint16 and color.shape == (h, w, 3)
        for sensor, profile, data, bpp in (
            (self.depth_sensor, self.depth_profile, np.ascontiguousarray(depth), 2),
            (self.color_sensor, self.color_profile, np.ascontiguousarray(color, dtype=np.uint8), 3),
        ):
            frame = rs.software_video_frame()
            frame.pixels, frame.bpp, frame.stride = data, bpp, w * bpp
            frame.timestamp, frame.domain, frame.frame_number = self.stamp_ms(k), rs.timestamp_domain.global_time, k + 1
            frame.profile = profile.as_video_stream_profile()
            if sensor is self.depth_sensor:
                frame.depth_units = self.depth_units
            self._keep = [*self._keep[-7:], data]
            sensor.on_video_frame(frame)
        self.sent += 1


class _SoftwareDeviceHandle:
    """The software_device, with the colour sensor found by its stream (see SoftwareRealSense)."""

    def __init__(self, device, color_sensor):
        self._device, self._color_sensor = device, color_sensor

    def first_color_sensor(self):
        return self._color_sensor

    def __getattr__(self, name):
        return getattr(self._device, name)


class _SoftwarePipeline:
    """start / wait_for_frames / stop over the software device's sensors and a real ``rs.syncer``."""

    def __init__(self, rig: SoftwareRealSense):
        self.rig, self.syncer = rig, None

    def start(self, cfg):
        rig = self.rig
        self.syncer = rig.rs.syncer()
        for sensor, profile in ((rig.depth_sensor, rig.depth_profile), (rig.color_sensor, rig.color_profile)):
            sensor.open(profile)
            sensor.start(self.syncer)
        return NS(get_device=lambda: rig.handle)

    def wait_for_frames(self, timeout_ms: int):
        # The syncer hands out the very first frame alone (it has not seen the other stream yet);
        # a pipeline's first framesets can be incomplete the same way. Push until a pair comes out.
        for _ in range(3):
            self.rig.push()
            frames = self.syncer.wait_for_frames(timeout_ms).as_frameset()
            if frames.size() == 2:
                return frames
        raise RuntimeError("software device: no complete frameset")

    def stop(self):
        for sensor in (self.rig.depth_sensor, self.rig.color_sensor):
            sensor.stop()
            sensor.close()
