"""`equidiff cameras list`: the RealSense devices on the bus and whether lab.yaml's cameras are among them.

Per device: serial, name, firmware and USB link (pyrealsense2's camera_info); a device on a
USB 2 link gets a warning line (a D4xx cannot stream depth at our resolution and rate over
it). Per lab.yaml camera: connected or not; a serial that is not on the bus gets one error
line naming it and the serials that are. Exit status 1 when a lab.yaml camera is missing.
It only enumerates devices and opens no stream.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from equidiff_core.cameras.realsense.devices import connected_devices, usb2_warning
from equidiff_core.config import default_config_dir, load_lab_config


def add_arguments(parser) -> None:
    parser.add_argument("--lab-config", type=Path, default=None, help="lab.yaml (default: the installed one)")
    parser.add_argument("--json", action="store_true", help="one JSON line instead of text")


def lab_report(lab_cameras, devices) -> tuple[list[dict], list[str], list[str]]:
    """(per lab camera: name, serial, connected), warning lines, error lines."""
    by_serial = {d.serial: d for d in devices}
    cameras = [{"name": c.name, "serial": c.serial, "connected": c.serial in by_serial} for c in lab_cameras]
    names = {c.serial: c.name for c in lab_cameras}
    warnings = []
    for device in devices:
        cam = next((c for c in lab_cameras if c.serial == device.serial), None)
        stream = f"depth at {cam.width}x{cam.height}@{cam.fps}" if cam else "depth at 848x480@30"
        line = usb2_warning(device, stream)
        if line:
            warnings.append(f"{names[device.serial]}: {line}" if device.serial in names else line)
    connected = ", ".join(sorted(by_serial)) or "none"
    errors = [
        f"{c['name']}: serial {c['serial']} from lab.yaml is not connected; connected RealSense serials: {connected}"
        for c in cameras
        if not c["connected"]
    ]
    return cameras, warnings, errors


def run(args) -> int:
    lab = load_lab_config(args.lab_config or default_config_dir() / "lab.yaml")
    try:  # the RealSense SDK is a lab machine's extra: named if missing
        import pyrealsense2 as rs
    except ImportError as err:
        print(
            f"equidiff cameras list: pyrealsense2 is not installed (pip install pyrealsense2): {err}", file=sys.stderr
        )
        return 1
    devices = [info for info, _ in connected_devices(rs, rs.context())]
    cameras, warnings, errors = lab_report(lab.cameras, devices)
    if args.json:
        print(
            json.dumps(
                {
                    "devices": [
                        {"serial": d.serial, "name": d.name, "firmware": d.firmware, "usb_type": d.usb_type}
                        for d in devices
                    ],
                    "lab_cameras": cameras,
                    "warnings": warnings,
                    "errors": errors,
                }
            )
        )
    else:
        lab_names = {c["serial"]: c["name"] for c in cameras}
        print(f"RealSense devices connected: {len(devices)}")
        for d in devices:
            print(
                f"  {d.serial}  {d.name}  firmware {d.firmware}  USB {d.usb_type}  "
                f"({lab_names.get(d.serial, 'not in lab.yaml')})"
            )
        print(f"lab.yaml cameras ({args.lab_config or 'installed lab.yaml'}):")
        for c in cameras:
            print(f"  {c['name']}  {c['serial']}  {'connected' if c['connected'] else 'NOT CONNECTED'}")
        for line in warnings:
            print(f"warning: {line}")
        for line in errors:
            print(f"error: {line}", file=sys.stderr)
    return 1 if errors else 0
