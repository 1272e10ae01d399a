"""The wire formats every node shares, built and read with both rclpy and rosbags messages."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from equidiff_core import geometry
from equidiff_core.wire.chunk import (
    ChunkError,
    chunk_from_actions,
    chunk_from_msg,
    chunk_to_msg,
)
from equidiff_core.wire.pointcloud import (
    CloudError,
    cloud_to_msg,
    grid_to_voxel_msg,
    msg_to_cloud,
    voxel_msg_to_grid,
)
from equidiff_core.wire.rosmsg import RclpyFactory, rosbags_factory


@pytest.fixture(params=["rclpy", "rosbags"])
def factory(request):
    return RclpyFactory() if request.param == "rclpy" else rosbags_factory()


def _cdr_round_trip(msg, type_name):
    """Serialise a rosbags message to CDR and back, as a bag does."""
    ts = rosbags_factory().typestore
    return ts.deserialize_cdr(ts.serialize_cdr(msg, type_name), type_name)


def test_cloud_round_trip(factory):
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(100, 3)).astype(np.float32)
    cols = rng.integers(0, 256, (100, 3), dtype=np.uint8)
    msg = cloud_to_msg(pts, cols, 1_700_000_000_123_456_789, "cam_optical", factory)
    if isinstance(factory, RclpyFactory):
        assert type(msg).__module__.startswith("sensor_msgs")
    else:
        msg = _cdr_round_trip(msg, "sensor_msgs/msg/PointCloud2")
    cloud = msg_to_cloud(msg)
    np.testing.assert_array_equal(cloud.points, pts)
    np.testing.assert_array_equal(cloud.colors, cols)
    assert cloud.stamp_ns == 1_700_000_000_123_456_789 and cloud.frame_id == "cam_optical"


def test_voxel_grid_round_trip_is_exact(factory):
    rng = np.random.default_rng(1)
    grid = np.zeros((4, 64, 64, 64), dtype=np.uint8)
    occ = rng.random((64, 64, 64)) < 0.02
    grid[0][occ] = 255
    grid[1:, occ] = rng.integers(0, 256, (3, occ.sum()), dtype=np.uint8)
    msg = grid_to_voxel_msg(grid, np.array([0.25, -0.2, -0.02]), 0.4 / 64, 42, "fr3_link0", factory)
    if not isinstance(factory, RclpyFactory):
        msg = _cdr_round_trip(msg, "sensor_msgs/msg/PointCloud2")
    np.testing.assert_array_equal(voxel_msg_to_grid(msg, 64), grid)
    # the same message is also a plain coloured cloud at the voxel centres
    cloud = msg_to_cloud(msg)
    assert len(cloud.points) == occ.sum()


def test_malformed_clouds_raise_clear_errors():
    f = rosbags_factory()
    good = cloud_to_msg(np.zeros((4, 3), np.float32), np.zeros((4, 3), np.uint8), 0, "c", f)
    no_z = cloud_to_msg(np.zeros((4, 3), np.float32), np.zeros((4, 3), np.uint8), 0, "c", f)
    no_z.fields = [fl for fl in no_z.fields if fl.name != "z"]
    with pytest.raises(CloudError, match=r"lacks field\(s\) \['z'\]"):
        msg_to_cloud(no_z)
    truncated = cloud_to_msg(np.zeros((4, 3), np.float32), np.zeros((4, 3), np.uint8), 0, "c", f)
    truncated.data = truncated.data[:-3]
    with pytest.raises(CloudError, match="bytes"):
        msg_to_cloud(truncated)
    bad_step = cloud_to_msg(np.zeros((4, 3), np.float32), np.zeros((4, 3), np.uint8), 0, "c", f)
    bad_step.point_step = 8
    with pytest.raises(CloudError):
        msg_to_cloud(bad_step)
    nan = cloud_to_msg(np.full((4, 3), np.nan, np.float32), np.zeros((4, 3), np.uint8), 0, "c", f)
    with pytest.raises(CloudError, match="NaN"):
        msg_to_cloud(nan)
    empty = cloud_to_msg(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8), 0, "c", f)
    with pytest.raises(CloudError, match="zero points"):
        msg_to_cloud(empty)
    assert len(msg_to_cloud(good).points) == 4


def test_chunk_round_trip(factory):
    R = Rotation.random(8, random_state=2).as_matrix()
    poses = geometry.make_pose(R, np.random.default_rng(2).uniform(-0.5, 0.5, (8, 3)))
    actions = geometry.pose_to_action(poses, np.linspace(0.0, 0.08, 8))
    chunk = chunk_from_actions(actions, stamp_ns=5_000_000_000, dt_ns=200_000_000)
    msg = chunk_to_msg(chunk, factory, "fr3_link0")
    if not isinstance(factory, RclpyFactory):
        msg = _cdr_round_trip(msg, "trajectory_msgs/msg/MultiDOFJointTrajectory")
    back = chunk_from_msg(msg)
    np.testing.assert_array_equal(back.times_ns, 5_000_000_000 + 200_000_000 * np.arange(8))
    np.testing.assert_allclose(back.poses, poses, atol=1e-9)
    np.testing.assert_allclose(back.widths, np.linspace(0.0, 0.08, 8))
    assert len(back.after(5_000_000_000 + 200_000_000 * 5)) == 2
    assert back.after(10**12) is None


def test_bad_chunks_are_rejected():
    f = rosbags_factory()
    a = geometry.pose_to_action(np.eye(4)[None].repeat(3, 0), np.zeros(3))
    msg = chunk_to_msg(chunk_from_actions(a, 0, 10), f, "b")
    msg.points[1].transforms[0].rotation.w = float("nan")
    with pytest.raises(ChunkError, match="NaN"):
        chunk_from_msg(msg)
    msg = chunk_to_msg(chunk_from_actions(a, 0, 10), f, "b")
    msg.points[2].transforms[0].rotation.w = 3.0
    with pytest.raises(ChunkError, match="unit length"):
        chunk_from_msg(msg)
    a[1, 3:9] = [1, 0, 0, 1, 0, 0]
    with pytest.raises(ChunkError, match="actions invalid"):
        chunk_from_actions(a, 0, 10)
