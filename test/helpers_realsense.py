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
