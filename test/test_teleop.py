"""TeleopIntegrator: deadzone, scaling, frames, rotation lock, gripper buttons, workspace clamp, lead limit."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from equidiff_core import geometry
from equidiff_core.chunk import chunk_from_msg, chunk_to_msg
from equidiff_core.config import Workspace
from equidiff_core.rosmsg import rosbags_factory
from equidiff_core.teleop import (
    SpaceMouseSource,
    TeleopConfig,
    TeleopError,
    TeleopInput,
    TeleopIntegrator,
    apply_deadzone,
    is_fresh,
)

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


@pytest.mark.parametrize("mode, presses, expected", [
    ("buttons", [(0, 1), (0, 0), (0, 1), (1, 0)], [0.0, 0.0, 0.0, 0.08]),
    ("toggle", [(1, 0), (0, 0), (1, 0), (1, 0), (0, 0), (0, 1)], [0.0, 0.0, 0.08, 0.08, 0.08, 0.0]),
    ("hold", [(0, 1), (0, 1), (0, 0), (1, 0)], [0.0, 0.0, 0.08, 0.08]),
])
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
    msg = f.make("sensor_msgs/msg/Joy", header=f.header(2_000_000_123, ""),
                 axes=np.array([0.1, 0.2, 0.3, 0.4, 0.5, 0.6], np.float32), buttons=np.array([1, 0], np.int32))
    inp = TeleopInput.from_joy(msg)
    np.testing.assert_allclose(inp.axes, [0.1, 0.2, 0.3, 0.4, 0.5, 0.6], atol=1e-6)
    assert inp.buttons == (1, 0) and inp.stamp_ns == 2_000_000_123
    short = f.make("sensor_msgs/msg/Joy", header=f.header(0, ""), axes=np.zeros(3, np.float32),
                   buttons=np.zeros(0, np.int32))
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
