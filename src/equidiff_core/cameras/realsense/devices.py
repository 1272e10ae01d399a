"""The RealSense devices on the bus: serial, name, firmware and USB link, from pyrealsense2's camera_info.

Used by ``RealSenseCamera`` to find its device by serial and by ``equidiff cameras list``.
``rs`` is the pyrealsense2 module and ``ctx`` an ``rs.context()``, passed in so that the
caller decides when the (optional) library is imported.
"""

from __future__ import annotations

from dataclasses import dataclass

UNKNOWN = "unknown"


@dataclass(frozen=True)
class DeviceInfo:
    serial: str
    name: str  # e.g. "Intel RealSense D455"
    firmware: str  # e.g. "5.16.0.1"
    usb_type: str  # the USB link's version, e.g. "3.2" or "2.1"; "unknown" when not reported

    @property
    def is_usb2(self) -> bool:
        return self.usb_type.startswith("2")


def _info(rs, device, field: str) -> str:
    key = getattr(rs.camera_info, field)
    return device.get_info(key) if device.supports(key) else UNKNOWN


def device_info(rs, device) -> DeviceInfo:
    return DeviceInfo(
        serial=_info(rs, device, "serial_number"),
        name=_info(rs, device, "name"),
        firmware=_info(rs, device, "firmware_version"),
        usb_type=_info(rs, device, "usb_type_descriptor"),
    )


def connected_devices(rs, ctx) -> list[tuple[DeviceInfo, object]]:
    """(info, device handle) of every RealSense enumerated now."""
    return [(device_info(rs, d), d) for d in ctx.query_devices()]


def find_device(rs, ctx, serial: str):
    """The device handle with ``serial``, or None when it is not enumerated."""
    for info, device in connected_devices(rs, ctx):
        if info.serial == serial:
            return device
    return None


def usb2_warning(info: DeviceInfo, stream: str = "depth + colour at 848x480@30") -> str | None:
    """One line when the device runs over USB 2, which cannot carry a D4xx's depth at our rate."""
    if not info.is_usb2:
        return None
    return (
        f"RealSense {info.serial} ({info.name}) is on a USB {info.usb_type} link: a D4xx needs USB 3 "
        f"for {stream}; plug it into a USB 3 port with a USB 3 cable"
    )
