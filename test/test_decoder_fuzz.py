"""Fuzzed decoders and chunk validation: a message either decodes to exactly what was encoded, or
raises the decoder's documented error (``CloudError``, ``ChunkError``, ``MessageError``) with a
message: never another exception, never a silently wrong value. Small budgets: each test runs in
seconds."""

from __future__ import annotations

import numpy as np
import pytest
from helpers_bad_messages import (
    bad_chunks,
    bad_clouds,
    bad_ee_poses,
    bad_joint_states,
    bad_voxel_msgs,
    robot_state,
    voxel_msg,
)
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from equidiff_core import geometry
from equidiff_core.config import Workspace
from equidiff_core.control import ChunkScheduler, SchedulerConfig
from equidiff_core.robots.base import ARM_JOINT_NAMES, FINGER_JOINT_NAMES, RobotState
from equidiff_core.wire.chunk import ChunkError, ChunkReason, PoseChunk, chunk_from_msg, chunk_to_msg
from equidiff_core.wire.pointcloud import (
    CloudError,
    VoxelGridSpec,
    check_voxel_msg,
    cloud_to_msg,
    msg_to_cloud,
    voxel_msg_to_grid,
)
from equidiff_core.wire.rosmsg import (
    GRIPPER_WIDTH_SLACK_M,
    MessageError,
    MessageReason,
    arm_joint_positions,
    check_not_future,
    diagnostic_array,
    diagnostic_entries,
    gripper_width_from_joint_state,
    has_gripper_joints,
    header_stamp_ns_from_cdr,
    joint_state,
    pos_quat_from_msg,
    pose_from_msg,
    pose_from_transform,
    pose_stamped,
    position_from_msg,
    rosbags_factory,
    tf_message,
    transform_msg,
)

FUZZ = settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow])
WS = Workspace(resolution=16)  # a small grid: the checks are the same at 64
SPEC = VoxelGridSpec.of(WS, "base")
NOW = 1_800_000_000 * 10**9
F = rosbags_factory()


def _refused(decode, msg, error):
    """Decode ``msg``; the value, or None when it raised ``error`` with a message (anything else fails)."""
    try:
        return decode(msg)
    except error as err:
        assert str(err), "an error without a message"
        return None


# --- round trips --------------------------------------------------------------------------

grids = hnp.arrays(np.uint8, (4, WS.resolution, WS.resolution, WS.resolution), elements=st.sampled_from([0, 7, 255]))


@FUZZ
@given(grid=grids)
def test_voxel_grid_round_trips(grid):
    grid = grid.copy()
    grid[0] = np.where(grid[0] > 0, 255, 0)  # the wire carries occupancy, not a level
    grid[1:, grid[0] == 0] = 0
    np.testing.assert_array_equal(voxel_msg_to_grid(voxel_msg(F, grid, WS, NOW, "base"), SPEC), grid)


finite = st.floats(-10, 10, allow_nan=False, width=32)


@FUZZ
@given(
    points=hnp.arrays(np.float32, st.tuples(st.integers(1, 50), st.just(3)), elements=finite),
    data=st.data(),
)
def test_camera_cloud_round_trips(points, data):
    colors = data.draw(hnp.arrays(np.uint8, points.shape))
    cloud = msg_to_cloud(cloud_to_msg(points, colors, NOW, "cam", F), frame_id="cam")
    np.testing.assert_array_equal(cloud.points, points)
    np.testing.assert_array_equal(cloud.colors, colors)
    assert cloud.stamp_ns == NOW and cloud.frame_id == "cam"


unit_quats = hnp.arrays(np.float64, 4, elements=st.floats(-1, 1)).filter(lambda q: np.linalg.norm(q) > 0.1)


@FUZZ
@given(
    steps=st.lists(
        st.tuples(hnp.arrays(np.float64, 3, elements=st.floats(-1, 1)), unit_quats, st.floats(0, 0.08)),
        min_size=1,
        max_size=8,
    ),
    dt_ns=st.integers(0, 10**9),
)
def test_chunk_round_trips(steps, dt_ns):
    poses = np.stack([geometry.pose_from_pos_quat(p, q / np.linalg.norm(q)) for p, q, _ in steps])
    times = NOW + np.arange(len(steps), dtype=np.int64) * dt_ns
    chunk = PoseChunk(NOW, times, poses, np.array([w for _, _, w in steps]))
    back = chunk_from_msg(chunk_to_msg(chunk, F, "base"), "base")
    np.testing.assert_array_equal(back.times_ns, chunk.times_ns)
    np.testing.assert_allclose(back.poses, chunk.poses, atol=1e-9)
    np.testing.assert_array_equal(back.widths, chunk.widths)


# --- mutated messages ---------------------------------------------------------------------


def _mutate_cloud(msg, data):
    """One random defect: a field's datatype, offset, count or name; point_step, width, height,
    row_step, endianness, the frame; the data truncated, extended or replaced by random bytes."""
    what = data.draw(
        st.sampled_from(
            [
                "datatype",
                "offset",
                "count",
                "name",
                "step",
                "width",
                "height",
                "row",
                "endian",
                "frame",
                "bytes",
                "drop",
            ]
        )
    )
    field = data.draw(st.sampled_from(list(msg.fields)))
    raw = bytes(msg.data)
    if what == "datatype":
        field.datatype = data.draw(st.integers(0, 10))
    elif what == "offset":
        field.offset = data.draw(st.integers(0, 40))
    elif what == "count":
        field.count = data.draw(st.integers(0, 4))
    elif what == "name":
        field.name = data.draw(st.sampled_from(["x", "y", "z", "rgb", "i", "j", "k", "", "rgba"]))
    elif what == "step":
        msg.point_step = data.draw(st.integers(0, 40))
    elif what == "width":
        msg.width = data.draw(st.integers(0, 2 * msg.width + 2))
    elif what == "height":
        msg.height = data.draw(st.integers(0, 3))
    elif what == "row":
        msg.row_step = data.draw(st.integers(0, 2 * msg.row_step + 2))
    elif what == "endian":
        msg.is_bigendian = True
    elif what == "frame":
        msg.header.frame_id = data.draw(st.text(max_size=8))
    elif what == "bytes":
        msg.data = np.frombuffer(data.draw(st.binary(min_size=len(raw), max_size=len(raw))), np.uint8)
    else:
        msg.data = np.frombuffer(raw[: data.draw(st.integers(0, len(raw)))], np.uint8)
    return msg


@FUZZ
@given(grid=grids, data=st.data())
def test_mutated_voxel_messages_decode_exactly_or_raise_cloud_error(grid, data):
    """A mutated voxel message decodes only to a grid the message really encodes: every occupied
    voxel at its index with its centre on the expected grid; otherwise CloudError."""
    grid = grid.copy()
    grid[0] = np.where(grid[0] > 0, 255, 0)
    grid[1:, grid[0] == 0] = 0
    msg = _mutate_cloud(voxel_msg(F, grid, WS, NOW, "base"), data)
    out = _refused(lambda m: voxel_msg_to_grid(m, SPEC), msg, CloudError)
    # the recorder's check without the grid refuses exactly what decoding refuses
    assert (_refused(lambda m: check_voxel_msg(m, SPEC), msg, CloudError) is None) == (out is None)
    if out is not None:  # e.g. random bytes that still form valid voxels: the grid must be exactly them
        assert out.shape == (4, WS.resolution, WS.resolution, WS.resolution) and out.dtype == np.uint8
        assert msg.header.frame_id == "base" and int(msg.point_step) == 24
        assert int(out[0].astype(bool).sum()) == int(msg.width) * int(msg.height)


@FUZZ
@given(
    points=hnp.arrays(np.float32, st.tuples(st.integers(1, 20), st.just(3)), elements=finite),
    data=st.data(),
)
def test_mutated_camera_clouds_decode_consistently_or_raise_cloud_error(points, data):
    colors = data.draw(hnp.arrays(np.uint8, points.shape))
    msg = _mutate_cloud(cloud_to_msg(points, colors, NOW, "cam", F), data)
    cloud = _refused(lambda m: msg_to_cloud(m, frame_id="cam"), msg, CloudError)
    if cloud is not None:  # never 400 points with 100 colours
        n = int(msg.width) * int(msg.height)
        assert cloud.points.shape == (n, 3) and cloud.colors.shape == (n, 3) and cloud.colors.dtype == np.uint8
        assert np.isfinite(cloud.points).all()


@pytest.mark.parametrize("kind", ["clouds", "voxels", "chunks", "ee_poses", "joint_states"])
def test_every_listed_bad_message_is_refused_with_its_error(kind):
    """The defects the live-node test publishes (helpers_bad_messages), each refused here too."""
    rng = np.random.default_rng(1)
    if kind == "clouds":
        points, colors = rng.random((400, 3)).astype(np.float32), rng.integers(0, 256, (400, 3), dtype=np.uint8)
        cases, decode, error = (
            bad_clouds(F, points, colors, NOW, "cam"),
            lambda m: msg_to_cloud(m, frame_id="cam"),
            CloudError,
        )
    elif kind == "voxels":
        ws = Workspace()
        grid = np.zeros((4, 64, 64, 64), np.uint8)
        grid[:, 20:26, 30:36, 2:8] = 255
        spec = VoxelGridSpec.of(ws, "base")
        cases, decode, error = (
            bad_voxel_msgs(F, grid, ws, NOW, "base"),
            lambda m: voxel_msg_to_grid(m, spec),
            CloudError,
        )
    elif kind == "chunks":
        cases = bad_chunks(F, (0.45, 0.0, 0.3), NOW, "base")
        decode, error = lambda m: ChunkScheduler().live_steps(chunk_from_msg(m, "base"), NOW), ChunkError
    elif kind == "ee_poses":
        pose = geometry.pose_from_pos_quat((0.45, 0.0, 0.3), (1.0, 0.0, 0.0, 0.0))
        cases, decode, error = bad_ee_poses(F, pose, NOW, "base"), lambda m: pose_from_msg(m, "base"), MessageError
    else:
        cases = bad_joint_states(F, robot_state((0.45, 0.0, 0.3)), NOW)
        decode, error = gripper_width_from_joint_state, MessageError
    for name, msg in cases.items():
        with pytest.raises(error, match=".") as err:
            decode(msg)
        assert err.value.reason, name


@FUZZ
@given(data=st.data())
def test_chunk_validation_refuses_what_it_must_and_nothing_else_escapes(data):
    """Random stamps, lengths, NaNs, non-orthonormal rotations, far-future and stale steps:
    a PoseChunk either builds and passes the scheduler's time checks, or ChunkError with a reason."""
    k = data.draw(st.integers(0, 6))
    poses = np.repeat(geometry.pose_from_pos_quat((0.45, 0.0, 0.3), (1.0, 0.0, 0.0, 0.0))[None], k, axis=0)
    times = NOW + np.sort(data.draw(hnp.arrays(np.int64, k, elements=st.integers(-2 * 10**9, 2 * 10**9))))
    widths = np.full(k, 0.04)
    stamp = NOW + data.draw(st.sampled_from([0, -(10**9), 10**7, 10**8, 86_400 * 10**9]))
    defect = data.draw(st.sampled_from(["none", "nan", "skew", "length", "order", "width"]))
    applied = True  # whether the drawn defect could be applied (some need steps)
    if k and defect == "nan":
        poses[data.draw(st.integers(0, k - 1)), 0, 3] = np.nan
    elif k and defect == "skew":
        poses[0, :3, :3] = poses[0, :3, :3] @ np.diag([1.0, 1.0 + data.draw(st.floats(0.01, 1.0)), 1.0])
    elif defect == "length":
        widths = np.full(k + 1, 0.04)
    elif k > 1 and defect == "order":
        times = times[::-1].copy()
        times[0] += 1
    elif k and defect == "width":
        widths[0] = np.inf
    else:
        applied = False
    config = SchedulerConfig()
    try:
        chunk = PoseChunk(int(stamp), times, poses, widths)
        live = ChunkScheduler(config).live_steps(chunk, NOW)
    except ChunkError as err:
        assert str(err) and isinstance(err.reason, ChunkReason)
        return
    # accepted: nothing was wrong with it
    assert not applied and k > 0 and np.isfinite(live.poses).all()
    assert chunk.stamp_ns - NOW <= config.max_future_stamp_s * 1e9
    assert live.times_ns[0] - NOW <= config.max_first_step_lead_s * 1e9
    assert NOW - chunk.times_ns[-1] <= config.max_step_age_s * 1e9


# --- robot state, transforms, diagnostics (rosmsg) -----------------------------------------

positions = hnp.arrays(np.float64, 3, elements=st.floats(-10, 10))
frames = st.text(min_size=1, max_size=12)
stamps = st.integers(0, 2**31 * 10**9 - 1)  # builtin_interfaces/Time: int32 seconds


def _unit(q: np.ndarray) -> np.ndarray:
    return q / np.linalg.norm(q)


@FUZZ
@given(position=positions, quat=unit_quats, frame=frames, stamp=stamps)
def test_pose_stamped_round_trips(position, quat, frame, stamp):
    pose = geometry.pose_from_pos_quat(position, _unit(quat))
    msg = pose_stamped(F, pose, stamp, frame)
    back = pose_from_msg(msg, frame)
    np.testing.assert_array_equal(back[:3, 3], position)  # the position travels as is
    np.testing.assert_allclose(back, pose, atol=1e-12)
    np.testing.assert_array_equal(position_from_msg(msg, frame), position)
    p, q = pos_quat_from_msg(msg, frame)
    o = msg.pose.orientation
    np.testing.assert_array_equal(q, [o.x, o.y, o.z, o.w])  # exactly as sent, not renormalised
    np.testing.assert_array_equal(p, position)


@FUZZ
@given(
    transforms=st.lists(st.tuples(frames, frames, positions, unit_quats), min_size=1, max_size=4),
    stamp=stamps,
)
def test_transforms_round_trip(transforms, stamp):
    poses = [geometry.pose_from_pos_quat(p, _unit(q)) for _, _, p, q in transforms]
    for pose in poses:
        np.testing.assert_allclose(pose_from_transform(transform_msg(F, pose)), pose, atol=1e-12)
    msg = tf_message(F, [(parent, child, pose) for (parent, child, _, _), pose in zip(transforms, poses)], stamp)
    assert len(msg.transforms) == len(transforms)
    for tf, (parent, child, _, _), pose in zip(msg.transforms, transforms, poses):
        np.testing.assert_allclose(pose_from_transform(tf, parent, child), pose, atol=1e-12)
        with pytest.raises(MessageError, match="child_frame_id") as err:
            pose_from_transform(tf, parent, child + "_other")
        assert err.value.reason == MessageReason.FRAME


@FUZZ
@given(
    q=hnp.arrays(np.float64, 7, elements=st.floats(-3, 3)),
    dq=hnp.arrays(np.float64, 7, elements=st.floats(-3, 3)),
    width=st.one_of(st.floats(0.0, 0.08, allow_subnormal=False), st.just(float("nan"))),
)
def test_joint_state_round_trips(q, dq, width):
    state = RobotState(NOW, np.eye(4), q, dq, width)
    msg = joint_state(F, state, NOW)
    np.testing.assert_array_equal(arm_joint_positions(msg), q)
    if np.isnan(width):  # an unknown width is left out, never sent as a width
        assert not has_gripper_joints(msg) and gripper_width_from_joint_state(msg) is None
    else:
        assert has_gripper_joints(msg) and gripper_width_from_joint_state(msg) == width


diag_values = st.dictionaries(
    st.text(min_size=1, max_size=10), st.one_of(st.text(max_size=10), st.integers(), st.booleans()), max_size=6
)


@pytest.mark.parametrize("flavour", ["rosbags", "rclpy"])
@FUZZ
@given(
    name=st.text(max_size=10),
    level=st.integers(0, 3),
    message=st.text(max_size=20),
    values=diag_values,
)
def test_diagnostic_array_round_trips(flavour, name, level, message, values):
    factory = F if flavour == "rosbags" else _rclpy_factory()
    (entry,) = diagnostic_entries(diagnostic_array(factory, NOW, name, "hw", level, message, values))
    assert (entry.name, entry.level, entry.message, entry.hardware_id) == (name, level, message, "hw")
    assert entry.values == {k: str(v) for k, v in values.items()}


def _rclpy_factory():
    pytest.importorskip("rclpy")
    from equidiff_core.wire.rosmsg import RclpyFactory

    return RclpyFactory()


def _cdr(msg, typename: str) -> bytes:
    return bytes(F.typestore.serialize_cdr(msg, typename))


@FUZZ
@given(stamp=stamps, frame=frames, cut=st.integers(0, 11))
def test_header_stamp_from_cdr_round_trips_and_refuses_truncated_bytes(stamp, frame, cut):
    pose = geometry.pose_from_pos_quat((0.1, 0.2, 0.3), (0.0, 0.0, 0.0, 1.0))
    data = _cdr(pose_stamped(F, pose, stamp, frame), "geometry_msgs/msg/PoseStamped")
    assert header_stamp_ns_from_cdr(data) == stamp
    with pytest.raises(MessageError, match="ends before"):
        header_stamp_ns_from_cdr(data[:cut])


@FUZZ
@given(data=st.binary(max_size=24))
def test_header_stamp_from_random_bytes_is_a_stamp_or_message_error(data):
    stamp = _refused(header_stamp_ns_from_cdr, data, MessageError)
    if stamp is not None:  # 12 bytes or more whose nanoseconds are below a second
        assert len(data) >= 12 and 0 <= stamp % 10**9 < 10**9


def _mutate_pose(msg, data):
    """One random defect: a NaN / inf or arbitrary value in any of the seven numbers, the quaternion
    scaled, or another frame."""
    what = data.draw(st.sampled_from(["value", "scale", "frame"]))
    pose = msg.pose
    if what == "value":
        part, axis = data.draw(st.sampled_from([("position", a) for a in "xyz"] + [("orientation", a) for a in "xyzw"]))
        value = data.draw(st.one_of(st.sampled_from([np.nan, np.inf, -np.inf]), st.floats(-2, 2)))
        setattr(getattr(pose, part), axis, value)
    elif what == "scale":
        factor = data.draw(st.floats(0.0, 3.0))
        o = pose.orientation
        o.x, o.y, o.z, o.w = o.x * factor, o.y * factor, o.z * factor, o.w * factor
    else:
        msg.header.frame_id = data.draw(st.text(max_size=8))
    return msg


@FUZZ
@given(position=positions, quat=unit_quats, data=st.data())
def test_mutated_poses_decode_exactly_or_raise_message_error(position, quat, data):
    msg = _mutate_pose(pose_stamped(F, geometry.pose_from_pos_quat(position, _unit(quat)), NOW, "base"), data)
    out = _refused(lambda m: pos_quat_from_msg(m, "base"), msg, MessageError)
    p, o = msg.pose.position, msg.pose.orientation
    sent_p, sent_q = np.array([p.x, p.y, p.z]), np.array([o.x, o.y, o.z, o.w])
    usable = (
        msg.header.frame_id == "base"
        and np.isfinite(sent_p).all()
        and np.isfinite(sent_q).all()
        and abs(np.linalg.norm(sent_q) - 1.0) <= 1e-3
    )
    assert (out is not None) == usable, (msg, out)
    if out is not None:
        np.testing.assert_array_equal(out[0], sent_p)
        np.testing.assert_array_equal(out[1], sent_q)
    else:
        with pytest.raises(MessageError) as err:
            pose_from_msg(msg, "base")
        assert isinstance(err.value.reason, MessageReason)


def _mutate_joint_state(msg, data):
    """One random defect: a position dropped or added, a name repeated or renamed, a position set to
    NaN / inf / any value, the velocities' or efforts' length."""
    what = data.draw(st.sampled_from(["drop", "add", "repeat", "rename", "value", "velocity", "effort"]))
    names, positions = list(msg.name), list(msg.position)
    i = data.draw(st.integers(0, len(names) - 1))
    if what == "drop":
        del positions[i]
    elif what == "add":
        positions.append(0.0)
    elif what == "repeat":
        names[i] = names[data.draw(st.integers(0, len(names) - 1))]
    elif what == "rename":
        names[i] = data.draw(st.text(max_size=8))
    elif what == "value":
        positions[i] = data.draw(st.one_of(st.sampled_from([np.nan, np.inf, -np.inf]), st.floats(-0.2, 0.2)))
    elif what == "velocity":
        msg.velocity = F.float64_array(np.zeros(data.draw(st.integers(0, len(names) + 2))))
    else:
        msg.effort = F.float64_array(np.zeros(data.draw(st.integers(0, len(names) + 2))))
    msg.name, msg.position = names, F.float64_array(positions)
    return msg


@FUZZ
@given(width=st.floats(0.0, 0.08, allow_subnormal=False), data=st.data())
def test_mutated_joint_states_decode_exactly_or_raise_message_error(width, data):
    msg = _mutate_joint_state(joint_state(F, robot_state((0.45, 0.0, 0.3), width), NOW), data)
    out = _refused(gripper_width_from_joint_state, msg, MessageError)
    names, positions = list(msg.name), np.asarray(msg.position)
    well_formed = (
        len(names) == len(positions)
        and len(set(names)) == len(names)
        and len(msg.velocity) in (0, len(names))
        and len(msg.effort) in (0, len(names))
        and np.isfinite(positions).all()
    )
    if not well_formed:
        assert out is None
        for decode in (arm_joint_positions, has_gripper_joints):
            with pytest.raises(MessageError):
                decode(msg)
        return
    by_name = dict(zip(names, positions))
    arm = arm_joint_positions(msg)
    if all(n in by_name for n in ARM_JOINT_NAMES):
        np.testing.assert_array_equal(arm, [by_name[n] for n in ARM_JOINT_NAMES])
    else:
        assert arm is None
    if not all(n in by_name for n in FINGER_JOINT_NAMES):
        assert out is None and not has_gripper_joints(msg)
        return
    sent = by_name[FINGER_JOINT_NAMES[0]] + by_name[FINGER_JOINT_NAMES[1]]
    in_stroke = -GRIPPER_WIDTH_SLACK_M <= sent <= 0.08 + GRIPPER_WIDTH_SLACK_M
    assert (out == sent) if in_stroke else out is None


@FUZZ
@given(values=diag_values, data=st.data())
def test_mutated_diagnostics_decode_exactly_or_raise_message_error(values, data):
    msg = diagnostic_array(F, NOW, "node", "", 0, "ok", values)
    status = msg.status[0]
    what = data.draw(st.sampled_from(["level", "empty_key", "repeated_key", "none"]))
    if what == "level":
        status.level = data.draw(st.integers(0, 255))
    elif what == "empty_key":
        status.values = [*status.values, F.make("diagnostic_msgs/msg/KeyValue", key="", value="1")]
    elif what == "repeated_key" and status.values:
        status.values = [*status.values, status.values[0]]
    out = _refused(diagnostic_entries, msg, MessageError)
    keys = [kv.key for kv in status.values]
    usable = int(status.level) <= 3 and all(keys) and len(set(keys)) == len(keys)
    assert (out is not None) == usable
    if out is not None:
        (entry,) = out
        assert entry.level == int(status.level) and entry.values == {kv.key: kv.value for kv in status.values}


def test_a_state_stamped_beyond_the_future_bound_is_refused():
    check_not_future(NOW + 50_000_000, NOW, 50_000_000, "a pose")  # at the bound: taken
    with pytest.raises(MessageError, match="ahead of this node's clock") as err:
        check_not_future(NOW + 50_000_001, NOW, 50_000_000, "a pose")
    assert err.value.reason == MessageReason.FUTURE
