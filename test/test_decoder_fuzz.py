"""Fuzzed decoders and chunk validation: a message either decodes to exactly what was encoded, or
raises the decoder's documented error (``CloudError``, ``ChunkError``) with a message: never
another exception, never a silently wrong value. Small budgets: each test runs in seconds."""

from __future__ import annotations

import numpy as np
import pytest
from helpers_bad_messages import bad_chunks, bad_clouds, bad_voxel_msgs, voxel_msg
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from equidiff_core import geometry
from equidiff_core.chunk import ChunkError, ChunkReason, PoseChunk, chunk_from_msg, chunk_to_msg
from equidiff_core.config import Workspace
from equidiff_core.control import ChunkScheduler, SchedulerConfig
from equidiff_core.pointcloud import CloudError, VoxelGridSpec, cloud_to_msg, msg_to_cloud, voxel_msg_to_grid
from equidiff_core.rosmsg import rosbags_factory

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


@pytest.mark.parametrize("kind", ["clouds", "voxels", "chunks"])
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
    else:
        cases = bad_chunks(F, (0.45, 0.0, 0.3), NOW, "base")
        decode, error = lambda m: ChunkScheduler().live_steps(chunk_from_msg(m, "base"), NOW), ChunkError
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
