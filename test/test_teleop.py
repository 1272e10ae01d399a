"""TeleopIntegrator: deadzone, scaling, frames, rotation lock, gripper buttons, workspace clamp, lead limit."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from equidiff_core import geometry
from equidiff_core.config import Workspace
from equidiff_core.lab.teleop import (
    SpaceMouseSource,
    TeleopConfig,
    TeleopError,
    TeleopInput,
    TeleopIntegrator,
    apply_deadzone,
    is_fresh,
)
from equidiff_core.wire.chunk import chunk_from_msg, chunk_to_msg
from equidiff_core.wire.rosmsg import rosbags_factory

NS = 1_000_000_000
WS = Workspace(center=(0.45, 0.0, 0.18), edge=0.4, resolution=64)
DOWN = np.diag([1.0, -1.0, -1.0])


def make(**kw) -> TeleopIntegrator:
    kw.setdefault("max_lead_m", 0.0)
    kw.setdefault("max_lead_rad", 0.0)
    t = TeleopIntegrator(TeleopConfig(**kw), WS)
    t.reset(geometry.make_pose(DOWN, [0.45, 0.0, 0.2]), 0.08)
    return t


def run(t: TeleopIntegrator, axes, seconds=1.0, dt=0.01, buttons=()):
    for _ in range(round(seconds / dt)):
        t.step(TeleopInput(tuple(axes), tuple(buttons)), dt)
    return t.target


def test_deadzone_is_continuous_and_reaches_full_scale():
    dz = 0.1
    out = apply_deadzone(np.array([0.05, -0.1, 0.1 + 1e-9, 0.55, -1.0, 2.0]), dz)
    np.testing.assert_allclose(out[:3], 0.0, atol=1e-8)
    assert out[3] == pytest.approx(0.5)
    assert out[4] == -1.0 and out[5] == 1.0  # clipped to the normalised range


def test_per_axis_scaling_in_metres_per_second():
    t = make(linear_scale=(0.1, 0.2, 0.05), deadzone=0.0)
    T = run(t, [1, 1, 1, 0, 0, 0], seconds=0.5)
    np.testing.assert_allclose(T[:3, 3], [0.45 + 0.05, 0.1, 0.2 + 0.025], atol=1e-9)
    np.testing.assert_allclose(T[:3, :3], DOWN, atol=1e-9)


def test_tool_frame_translation_follows_the_tcp_axes():
    base = make(translation_frame="base", deadzone=0.0, linear_scale=(0.1, 0.1, 0.1))
    tool = make(translation_frame="tool", deadzone=0.0, linear_scale=(0.1, 0.1, 0.1))
    run(base, [0, 0, 0.5, 0, 0, 0], seconds=0.2)
    run(tool, [0, 0, 0.5, 0, 0, 0], seconds=0.2)
    # base +z is up; the downward-pointing tool's +z is down
    assert base.target[2, 3] == pytest.approx(0.21)
    assert tool.target[2, 3] == pytest.approx(0.19)


def test_rotation_rate_frames_and_lock():
    t = make(deadzone=0.0, angular_scale=(1.0, 1.0, 0.5))
    z0 = run(t, [0, 0, 1, 0, 0, 0.0], seconds=0.1)[2, 3]
    T = run(t, [0, 0, 0, 0, 0, 1.0], seconds=1.0)  # yaw 0.5 rad about base z
    rel = Rotation.from_matrix(T[:3, :3] @ DOWN.T).as_rotvec()
    np.testing.assert_allclose(rel, [0, 0, 0.5], atol=1e-6)
    assert z0 == pytest.approx(0.215) and T[2, 3] == pytest.approx(z0)  # position untouched by rotation (about the TCP)
    tool = make(deadzone=0.0, angular_scale=(1.0, 1.0, 0.5), rotation_frame="tool")
    Tt = run(tool, [0, 0, 0, 0, 0, 1.0], seconds=1.0)  # yaw about the tool z (pointing down)
    rel = Rotation.from_matrix(Tt[:3, :3] @ DOWN.T).as_rotvec()
    np.testing.assert_allclose(rel, [0, 0, -0.5], atol=1e-6)
    locked = make(deadzone=0.0, lock_rotation=True)
    Tl = run(locked, [0.5, 0, 0, 1, 1, 1], seconds=0.5)
    np.testing.assert_allclose(Tl[:3, :3], DOWN, atol=1e-12)
    assert Tl[0, 3] > 0.45


def test_long_integration_stays_a_proper_rotation():
    t = make(deadzone=0.0, angular_scale=(3.0, 3.0, 3.0))
    T = run(t, [0, 0, 0, 0.7, -0.4, 0.9], seconds=20.0, dt=0.005)
    geometry.validate_pose(T, tol=1e-9)


def test_target_stays_inside_the_workspace_box():
    t = make(deadzone=0.0, linear_scale=(0.5, 0.5, 0.5), workspace_margin=0.01)
    T = run(t, [1, -1, 1, 0, 0, 0], seconds=3.0)
    np.testing.assert_allclose(T[:3, 3], [WS.upper[0] - 0.01, WS.lower[1] + 0.01, WS.upper[2] - 0.01])


def test_reset_outside_the_box_clamps_the_start():
    t = TeleopIntegrator(TeleopConfig(), WS)
    t.reset(geometry.make_pose(DOWN, [0.45, 0.0, 0.9]))
    assert t.target[2, 3] == pytest.approx(WS.upper[2])


def test_target_never_leads_the_measured_pose_by_more_than_max_lead():
    t = make(deadzone=0.0, linear_scale=(0.5, 0.5, 0.5), max_lead_m=0.03, max_lead_rad=0.2)
    T = run(t, [1, 0, 0, 0, 0, 1], seconds=2.0)
    assert T[0, 3] == pytest.approx(0.48)
    rel = Rotation.from_matrix(T[:3, :3] @ DOWN.T).magnitude()
    assert rel == pytest.approx(0.2)
    t.observe(geometry.make_pose(DOWN, [0.47, 0.0, 0.2]))  # the arm catches up
    T = run(t, [1, 0, 0, 0, 0, 0], seconds=1.0)
    assert T[0, 3] == pytest.approx(0.50)


@pytest.mark.parametrize(
    "mode, presses, expected",
    [
        ("buttons", [(0, 1), (0, 0), (0, 1), (1, 0)], [0.0, 0.0, 0.0, 0.08]),
        ("toggle", [(1, 0), (0, 0), (1, 0), (1, 0), (0, 0), (0, 1)], [0.0, 0.0, 0.08, 0.08, 0.08, 0.0]),
        ("hold", [(0, 1), (0, 1), (0, 0), (1, 0)], [0.0, 0.0, 0.08, 0.08]),
    ],
)
def test_gripper_buttons(mode, presses, expected):
    t = make(gripper_mode=mode)
    widths = [t.step(TeleopInput((0,) * 6, b), 0.01)[1] for b in presses]
    assert widths == expected


def test_reset_takes_gripper_state_from_measured_width():
    t = TeleopIntegrator(TeleopConfig(), WS)
    t.reset(geometry.make_pose(DOWN, [0.45, 0, 0.2]), measured_width=0.01)
    assert t.width == 0.0
    t.reset(geometry.make_pose(DOWN, [0.45, 0, 0.2]), measured_width=0.07)
    assert t.width == 0.08


def test_no_input_holds_and_bad_input_raises():
    t = make()
    before = t.target.copy()
    T, _ = t.step(None, 0.5)
    np.testing.assert_array_equal(T, before)
    with pytest.raises(TeleopError, match="6 finite axes"):
        t.step(TeleopInput((0.1, float("nan"), 0, 0, 0, 0)), 0.01)
    with pytest.raises(TeleopError, match="reset"):
        TeleopIntegrator(TeleopConfig(), WS).step(TeleopInput((0,) * 6), 0.01)


def test_chunk_is_one_point_ahead_and_round_trips_the_wire_format():
    t = make(command_lead_s=0.05)
    run(t, [0.5, 0, 0, 0, 0, 0.3], seconds=0.3)
    chunk = t.chunk(1_000_000_000)
    assert len(chunk) == 1 and chunk.times_ns[0] == 1_050_000_000
    back = chunk_from_msg(chunk_to_msg(chunk, rosbags_factory(), "fr3_link0"))
    np.testing.assert_allclose(back.poses, chunk.poses, atol=1e-9)
    assert back.widths[0] == t.width


def test_joy_input_parsing():
    f = rosbags_factory()
    msg = f.make(
        "sensor_msgs/msg/Joy",
        header=f.header(2_000_000_123, ""),
        axes=np.array([0.1, 0.2, 0.3, 0.4, 0.5, 0.6], np.float32),
        buttons=np.array([1, 0], np.int32),
    )
    inp = TeleopInput.from_joy(msg)
    np.testing.assert_allclose(inp.axes, [0.1, 0.2, 0.3, 0.4, 0.5, 0.6], atol=1e-6)
    assert inp.buttons == (1, 0) and inp.stamp_ns == 2_000_000_123
    short = f.make(
        "sensor_msgs/msg/Joy", header=f.header(0, ""), axes=np.zeros(3, np.float32), buttons=np.zeros(0, np.int32)
    )
    with pytest.raises(TeleopError, match="6"):
        TeleopInput.from_joy(short)
    assert is_fresh(inp, 2_100_000_000, 0.25) and not is_fresh(inp, 2_400_000_000, 0.25)


def test_config_validation():
    with pytest.raises(ValueError, match="100 Hz"):
        TeleopConfig(source="spacemouse", rate_hz=50)
    with pytest.raises(ValueError, match="gripper_mode"):
        TeleopConfig(gripper_mode="press")
    with pytest.raises(ValueError, match="frame"):
        TeleopConfig(translation_frame="world")


def test_spacemouse_absent_names_what_was_looked_for():
    # No HID device on this machine (and none in CI): the error must say what was searched.
    src = SpaceMouseSource()
    with pytest.raises(TeleopError) as err:
        src.connect()
    assert "SpaceMouse" in str(err.value)
    assert "3Dconnexion" in str(err.value) or "hidapi" in str(err.value) or "HID" in str(err.value)


def test_yaw_integrates_at_the_commanded_rate():
    t = make(deadzone=0.0, angular_scale=(0.0, 0.0, math.pi / 4))
    T = run(t, [0, 0, 0, 0, 0, 1], seconds=1.0, dt=0.002)
    yaw = math.atan2(T[1, 0], T[0, 0])
    assert yaw == pytest.approx(math.pi / 4, abs=1e-6)


# --- the device stops reporting: the motion stops input_timeout_s later ----------------------


class FakeClock:
    """pyspacemouse's report clock (``device.high_acc_clock``), advanced by the test, not the wall."""

    def __init__(self):
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


class ScriptedHid:
    """Stands in for the USB HID device (easyhid's ``Device``) under pyspacemouse's real
    ``SpaceMouseDevice``: non-blocking ``read`` returns the reports that are due, then nothing."""

    product_string = "SpaceMouse Compact (scripted)"
    manufacturer_string = "3Dconnexion"
    release_number = 1
    serial_number = ""

    def __init__(self, clock: FakeClock):
        self.clock = clock
        self.reports: list[tuple[float, bytes]] = []  # (due time s, raw report)

    def open(self):
        pass

    def close(self):
        pass

    def set_nonblocking(self, _on):
        pass

    def read(self, _size):
        if self.reports and self.reports[0][0] <= self.clock.t:
            return self.reports.pop(0)[1]
        return b""


def scripted_spacemouse(monkeypatch):
    """A SpaceMouse Compact in the ROS axis convention: pyspacemouse's parsing and report timing,
    our SpaceMouseSource, only the USB device scripted."""
    import pyspacemouse
    from pyspacemouse import device as spacemouse_device
    from pyspacemouse.config_helpers import apply_axis_convention

    clock = FakeClock()
    monkeypatch.setattr(spacemouse_device, "high_acc_clock", clock)
    spec = apply_axis_convention(pyspacemouse.get_device_specs()["SpaceMouseCompact"], pyspacemouse.AxisConvention.ROS)
    hid = ScriptedHid(clock)
    dev = spacemouse_device.SpaceMouseDevice(spec, hid)
    dev.open()
    return SpaceMouseSource(opened=dev), hid, clock


def translation_report(raw: int) -> bytes:
    """HID channel 1 (translation) with the first axis at ``raw`` (350 = full scale), others 0."""
    lo, hi = raw & 0xFF, (raw >> 8) & 0xFF
    return bytes([1, lo, hi, 0, 0, 0, 0])


def test_a_spacemouse_that_stops_reporting_stops_the_motion_within_the_timeout(monkeypatch):
    src, hid, clock = scripted_spacemouse(monkeypatch)
    src.connect()  # already open: only checked
    t = make(deadzone=0.0, linear_scale=(0.1, 0.1, 0.1))
    cfg = t.config
    assert cfg.input_timeout_s == 0.2
    last_report_s = clock.t + 1.0
    # full deflection, one report every 10 ms for 1 s; then the device goes silent with the
    # cap still deflected (a pulled cable, a hung receiver): its last state says "full speed"
    hid.reports = [(clock.t + 0.01 * k, translation_report(350)) for k in range(101)]
    tick_s, ticks = 0.005, 400
    start = t.target.copy()
    moved_at: list[float] = []
    for _ in range(ticks):
        clock.t += tick_s
        now = int(clock.t * NS)
        inp = src.read(now)
        before = t.target.copy()
        fresh = inp if is_fresh(inp, now, cfg.input_timeout_s) else None
        t.step(fresh if t.engaged(fresh) else None, tick_s)
        if not np.array_equal(before, t.target):
            moved_at.append(clock.t)
    axes = np.asarray(src.read(int(clock.t * NS)).axes)
    assert np.count_nonzero(axes) == 1 and abs(axes).max() == pytest.approx(1.0)  # still reads "deflected"
    assert np.linalg.norm(t.target[:3, 3] - start[:3, 3]) > 0.09  # it did drive while the device reported
    assert moved_at[-1] <= last_report_s + cfg.input_timeout_s + tick_s + 1e-9
    assert moved_at[-1] >= last_report_s  # not earlier: a steadily reporting device keeps driving


def test_a_spacemouse_that_never_reported_is_not_fresh(monkeypatch):
    src, _hid, clock = scripted_spacemouse(monkeypatch)
    inp = src.read(int(clock.t * NS))
    assert inp.stamp_ns == 0 and not is_fresh(inp, int(clock.t * NS), 0.2)


def test_spacemouse_report_stamp_is_its_age_on_the_callers_clock(monkeypatch):
    src, hid, clock = scripted_spacemouse(monkeypatch)
    hid.reports = [(clock.t, translation_report(175))]
    src.read(0)
    clock.t += 0.15  # the report is now 150 ms old
    inp = src.read(5 * NS)
    assert inp.stamp_ns == pytest.approx(5 * NS - 150_000_000, abs=1000)
    assert is_fresh(inp, 5 * NS, 0.2) and not is_fresh(inp, 5 * NS + 60_000_000, 0.2)


# --- clutch and rotation-enable buttons -------------------------------------------------------


def test_clutch_button_gates_all_motion_but_not_the_gripper():
    t = make(deadzone=0.0, clutch_button=2, gripper_mode="buttons")
    start = t.target.copy()
    released = TeleopInput((1, 0, 0, 0, 0, 1), (0, 0, 0))
    assert not t.engaged(released)
    run(t, released.axes, seconds=0.5, buttons=released.buttons)
    np.testing.assert_array_equal(t.target, start)
    T = run(t, released.axes, seconds=0.5, buttons=(0, 0, 1))
    assert t.engaged(TeleopInput(released.axes, (0, 0, 1)))
    assert T[0, 3] == pytest.approx(0.45 + 0.075)  # 0.15 m/s for 0.5 s
    assert Rotation.from_matrix(T[:3, :3] @ DOWN.T).magnitude() == pytest.approx(0.4)
    # the gripper buttons work with the clutch released (and count as the operator's input)
    assert t.engaged(TeleopInput((0,) * 6, (0, 1, 0)))
    assert t.step(TeleopInput((0,) * 6, (0, 1, 0)), 0.01)[1] == 0.0


def test_rotation_button_enables_rotation_translation_always_on():
    t = make(deadzone=0.0, rotation_button=2)
    T = run(t, [1, 0, 0, 0, 0, 1], seconds=0.2, buttons=(0, 0, 0))
    assert T[0, 3] == pytest.approx(0.48)
    np.testing.assert_allclose(T[:3, :3], DOWN, atol=1e-12)
    assert not t.engaged(TeleopInput((0, 0, 0, 0, 0, 1), (0, 0, 0)))  # rotation alone, not enabled
    T = run(t, [0, 0, 0, 0, 0, 1], seconds=0.5, buttons=(0, 0, 1))
    assert Rotation.from_matrix(T[:3, :3] @ DOWN.T).magnitude() == pytest.approx(0.4)


def test_clutch_configuration_is_checked():
    with pytest.raises(ValueError, match="gripper button"):
        TeleopConfig(clutch_button=1)
    with pytest.raises(ValueError, match="both 3"):
        TeleopConfig(clutch_button=3, rotation_button=3)
    with pytest.raises(ValueError, match="input_timeout_s"):
        TeleopConfig(input_timeout_s=0.0)
    assert TeleopConfig().clutch_button == -1 and TeleopConfig().rotation_button == -1  # off by default
