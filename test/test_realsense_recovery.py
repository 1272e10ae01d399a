"""The RealSense driver against a fake pyrealsense2 (helpers_realsense): stall -> reset -> reconnect, errors, `cameras list`."""

import json
import sys
from types import SimpleNamespace as NS

import numpy as np
import pytest
from helpers_realsense import FakeClock, FakeRealSense

from equidiff_core.cameras import CameraError, CameraHealth
from equidiff_core.cameras.realsense import RealSenseCamera
from equidiff_core.config import default_config_dir, load_lab_config

LAB = load_lab_config(default_config_dir() / "lab.yaml")
FRONT = LAB.cameras[0]  # decimation 2, spatial, temporal, exposure 8500 us, white balance 4600 K
# options on top of lab.yaml's so that every kind of setting is re-applied
EXTRA = {
    "laser_power": 150.0,
    "depth_exposure_us": 8000.0,
    "visual_preset": "high_accuracy",
    "reset_after_timeouts": 3,
    "reenumerate_timeout_s": 10.0,
    "reconnect_backoff_s": 1.0,
    "reconnect_backoff_max_s": 4.0,
}
EXPECTED_OPTIONS = {
    "depth": {
        "global_time_enabled": 1.0,
        "visual_preset": 3.0,
        "laser_power": 150.0,
        "enable_auto_exposure": 0.0,
        "exposure": 8000.0,
    },
    "color": {
        "global_time_enabled": 1.0,
        "enable_auto_exposure": 0.0,
        "exposure": 85.0,
        "enable_auto_white_balance": 0.0,
        "white_balance": 4600.0,
    },
}


@pytest.fixture
def bus(monkeypatch):
    depth = np.full((6, 8), 800, np.uint16)
    color = np.full((6, 8, 3), 7, np.uint8)
    fake = FakeRealSense(FakeClock(), depth, color, reset_s=3.0)
    monkeypatch.setitem(sys.modules, "pyrealsense2", fake.module)
    return fake


def _camera(bus, cfg=FRONT, **kw):
    return RealSenseCamera(cfg, monotonic=bus.clock.monotonic, sleep=bus.clock.sleep, **{**EXTRA, **kw})


def _read_until_frame(cam, max_reads=100):
    """Read as camera_node does (1 s timeout, errors collected) until a frame arrives."""
    errors = []
    for _ in range(max_reads):
        try:
            return cam.read(timeout_s=1.0), errors
        except CameraError as err:
            errors.append(str(err))
    raise AssertionError(f"no frame after {max_reads} reads: {errors[-3:]}")


def _filter_kinds(bus):
    return sorted(f.kind for f in bus.filters)


def test_a_stalled_camera_is_reset_reconnected_with_every_option_and_streams_again(bus):
    device = bus.plug(FRONT.serial)
    cam = _camera(bus)
    cam.connect()
    assert device.applied() == EXPECTED_OPTIONS
    first_filters = list(bus.filters)
    assert _filter_kinds(bus) == [
        "decimation_filter",
        "disparity_transform",
        "disparity_transform",
        "spatial_filter",
        "temporal_filter",
    ]
    assert first_filters[0].values == {"filter_magnitude": 2}
    assert len(cam.read().points) == 48 and cam.health() == CameraHealth()

    device.stalled = True
    errors, resets = [], []
    for _ in range(3):
        with pytest.raises(CameraError) as err:
            cam.read(timeout_s=1.0)
        errors.append(str(err.value))
        resets.append(device.resets)
    assert all(f"'cam_front' ({FRONT.serial}): no frame within 1.0 s" in e for e in errors)
    assert resets == [0, 0, 1] and "in a row" not in errors[1]
    assert "3 in a row: stream stopped, hardware reset, waiting up to 10.0 s" in errors[2]
    assert device.resets == 1 and device.applied() == {"depth": {}, "color": {}}  # the reset lost the settings
    assert cam.health().recovering and not cam.is_connected

    frame, recovering = _read_until_frame(cam)
    # while the device is off the bus (3 s on the fake clock), each read says what is happening
    assert recovering and all(
        "recovering after 3 frame timeouts in a row: hardware reset, waiting for the serial to re-enumerate" in e
        for e in recovering
    )
    assert len(frame.points) == 48
    assert device.applied() == EXPECTED_OPTIONS  # every option re-applied, by the same code as connect
    assert bus.starts == [FRONT.serial, FRONT.serial]
    assert len(bus.filters) == 2 * len(first_filters) and bus.filters[len(first_filters)].values == {
        "filter_magnitude": 2
    }
    assert cam.health() == CameraHealth(
        resets=1, reconnects=1, recovering=False, last_recovery_reason="3 frame timeouts in a row"
    )
    assert len(cam.read().points) == 48  # frames keep flowing
    assert cam.health().resets == 1


def test_an_unplugged_camera_is_retried_with_back_off_and_comes_back_when_plugged_in(bus):
    device = bus.plug(FRONT.serial)
    bus.plug("215122250009")  # another camera stays connected: the messages name it
    cam = _camera(bus)
    cam.connect()
    cam.read()
    device.plugged = False
    errors = []
    attempts_seen = []
    for _ in range(60):  # ~60 s on the fake clock
        with pytest.raises(CameraError) as err:
            cam.read(timeout_s=1.0)
        errors.append(str(err.value))
        if "next attempt in" in errors[-1]:
            attempts_seen.append(errors[-1].split("no frame after ")[1].split(" ")[0])
    assert "stream stopped, not on the bus (unplugged?)" in errors[2]
    assert device.resets == 0  # nothing to reset while it is gone
    gave_up = [e for e in errors if "has not come back" in e]
    assert gave_up and "connected RealSense serials: ['215122250009']" in gave_up[0]
    # one attempt = reenumerate_timeout_s (10 s) of waiting; the pause between attempts doubles up to 4 s
    assert sorted({int(n) for n in attempts_seen}) == [1, 2, 3, 4]
    assert any("next attempt in 4.0 s" in e for e in gave_up) and not any("next attempt in 5" in e for e in gave_up)
    assert cam.health().recovering and cam.health().reconnects == 0

    device.plugged = True
    frame, _ = _read_until_frame(cam)
    assert len(frame.points) == 48 and device.applied() == EXPECTED_OPTIONS
    assert cam.health() == CameraHealth(
        resets=0, reconnects=1, recovering=False, last_recovery_reason="3 frame timeouts in a row"
    )


def test_a_reset_that_does_not_cure_the_stall_backs_off_before_the_next_one(bus):
    device = bus.plug(FRONT.serial)
    device.fixed_by_reset = False
    cam = _camera(bus)
    cam.connect()
    device.stalled = True
    errors = []
    for _ in range(40):
        try:
            cam.read(timeout_s=1.0)
            raise AssertionError("a stalled device gave a frame")
        except CameraError as err:
            errors.append(str(err))
        if device.resets == 3:
            break
    assert device.resets == 3  # reset, reopen, no frame: the next reset comes after a pause
    assert any("the last reconnect brought no frame: next reset in 1.0 s" in e for e in errors)
    assert any("the last reconnect brought no frame: next reset in 2.0 s" in e for e in errors)
    assert cam.health().reconnects == 2  # the stream reopened each time, but no frame followed

    device.stalled = False
    frame, _ = _read_until_frame(cam)
    assert len(frame.points) == 48 and device.applied() == EXPECTED_OPTIONS
    assert not cam.health().recovering


def test_bad_serial_and_usb2_each_give_one_clear_line(bus):
    bus.plug("215122250009")
    with pytest.raises(CameraError) as err:
        _camera(bus).connect()
    assert str(err.value) == (
        f"RealSense camera 'cam_front' with serial {FRONT.serial} not found; "
        "connected RealSense serials: ['215122250009']"
    )
    bus.plug(FRONT.serial, usb_type="2.1")
    with pytest.raises(CameraError) as err:
        _camera(bus).connect()
    assert (
        f"({FRONT.serial}): cannot start 848x480@30: Couldn't resolve requests; RealSense {FRONT.serial} "
        "(Intel RealSense D455) is on a USB 2.1 link: a D4xx needs USB 3 for 848x480@30" in str(err.value)
    )
    assert "\n" not in str(err.value)


def test_recovery_options_are_validated():
    with pytest.raises(CameraError, match=r"reset_after_timeouts: 0 timeouts is out of range; allowed: 1 <= x <= 100"):
        RealSenseCamera(FRONT, reset_after_timeouts=0)
    with pytest.raises(CameraError, match="reconnect_backoff_max_s"):
        RealSenseCamera(FRONT, reconnect_backoff_s=5.0, reconnect_backoff_max_s=1.0)
    with pytest.raises(CameraError, match=r"reenumerate_timeout_s: 0.0 s is out of range"):
        RealSenseCamera(FRONT, reenumerate_timeout_s=0)


# --- equidiff cameras list ---------------------------------------------------------------------------


def _cameras_list(capsys, *argv):
    from equidiff_ros.cli import main

    rc = main(["cameras", "list", *argv])
    out = capsys.readouterr()
    return rc, out.out, out.err


def test_cameras_list_shows_each_device_and_names_usb2_links_and_missing_serials(bus, capsys):
    bus.plug(LAB.cameras[0].serial, firmware="5.16.0.1", usb_type="3.2")
    bus.plug(LAB.cameras[1].serial, firmware="5.15.1.0", usb_type="2.1")
    bus.plug("215122250009", usb_type="3.2")
    rc, out, err = _cameras_list(capsys)
    assert rc == 1  # cam_right is missing
    assert f"  {LAB.cameras[0].serial}  Intel RealSense D455  firmware 5.16.0.1  USB 3.2  (cam_front)" in out
    assert f"  {LAB.cameras[1].serial}  Intel RealSense D455  firmware 5.15.1.0  USB 2.1  (cam_left)" in out
    assert "  215122250009  Intel RealSense D455  firmware 5.16.0.1  USB 3.2  (not in lab.yaml)" in out
    assert f"  cam_right  {LAB.cameras[2].serial}  NOT CONNECTED" in out
    warnings = [line for line in out.splitlines() if line.startswith("warning:")]
    assert warnings == [
        (
            f"warning: cam_left: RealSense {LAB.cameras[1].serial} (Intel RealSense D455) is on a USB 2.1 "
            "link: a D4xx needs USB 3 for depth at 848x480@30; plug it into a USB 3 port with a USB 3 cable"
        )
    ]
    assert err.splitlines() == [
        (
            f"error: cam_right: serial {LAB.cameras[2].serial} from lab.yaml is not connected; "
            f"connected RealSense serials: 215122250001, 215122250002, 215122250009"
        )
    ]

    bus.plug(LAB.cameras[2].serial)
    rc, out, err = _cameras_list(capsys, "--json")
    report = json.loads(out)
    assert rc == 0 and err == "" and report["errors"] == [] and len(report["warnings"]) == 1
    assert [c["connected"] for c in report["lab_cameras"]] == [True, True, True]
    assert {d["serial"]: d["usb_type"] for d in report["devices"]}[LAB.cameras[1].serial] == "2.1"


def test_cameras_list_with_no_device_names_every_missing_serial(bus, capsys):
    rc, out, err = _cameras_list(capsys)
    assert rc == 1 and "RealSense devices connected: 0" in out
    assert [line.split(":")[1].strip() for line in err.splitlines()] == [c.name for c in LAB.cameras]
    assert all(line.endswith("connected RealSense serials: none") for line in err.splitlines())


def test_camera_node_diagnostics_carry_the_recovery_counters(bus, monkeypatch):
    """camera_node's /diagnostics values for a camera mid-recovery (the node's method, without a ROS graph)."""
    from equidiff_core.wire.rosmsg import rosbags_factory
    from equidiff_ros.camera_node import CameraNode

    device = bus.plug(FRONT.serial)
    cam = _camera(bus)
    cam.connect()
    device.stalled = True
    for _ in range(3):
        with pytest.raises(CameraError):
            cam.read(timeout_s=1.0)
    published = []
    node = NS(
        configs=[FRONT],
        cameras=[cam],
        stats={
            FRONT.name: {"published": 5, "read_errors": 3, "last_stamp_ns": None, "color_published": 0, "jpeg_s": 0.0}
        },
        backend="realsense",
        factory=rosbags_factory(),
        diag_pub=NS(publish=published.append),
    )
    monkeypatch.setattr("equidiff_ros.camera_node.now_ns", lambda _node: 10**9)
    CameraNode._publish_diagnostics(node)
    status = published[0].status[0]
    values = {kv.key: kv.value for kv in status.values}
    assert status.message == "recovering: 3 frame timeouts in a row"
    assert values["resets"] == "1" and values["reconnects"] == "0"
    assert values["last_recovery_reason"] == "3 frame timeouts in a row"
