"""`equidiff replay`: a live subscriber receives the bag's messages (original or re-stamped), and --robot."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from helpers_data import RosHarness, assert_same

from equidiff_core.data.bags import read_episode
from equidiff_core.wire.chunk import chunk_from_msg
from equidiff_core.wire.rosmsg import stamp_to_ns

pytestmark = [pytest.mark.ros, pytest.mark.slow]

BAG = Path(__file__).resolve().parents[1] / "bags" / "sample_pick_0000"
TOPICS = {
    "/voxels": "sensor_msgs/msg/PointCloud2",
    "/franka/ee_pose": "geometry_msgs/msg/PoseStamped",
    "/franka/command_chunk": "trajectory_msgs/msg/MultiDOFJointTrajectory",
    "/spacenav/joy": "sensor_msgs/msg/Joy",
    "/franka/joint_states": "sensor_msgs/msg/JointState",
}


@pytest.fixture
def ros(ros_domain):
    h = RosHarness()
    yield h
    h.close()


def replay(*args: str) -> subprocess.Popen:
    env = dict(os.environ, OMP_NUM_THREADS="1")
    return subprocess.Popen(
        [sys.executable, "-m", "equidiff_ros.cli", "replay", str(BAG), *args],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def collect(ros: RosHarness, proc: subprocess.Popen, topics, timeout=90.0):
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    deep = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)  # the test may stall under load
    got = {t: [] for t in topics}
    arrival = {t: [] for t in topics}
    for t in topics:

        def cb(m, t=t):
            got[t].append(m)
            arrival[t].append(time.monotonic())

        ros.node.create_subscription(ros.f.cls(TOPICS[t]), t, cb, deep)
    ros.spin_until(lambda: proc.poll() is not None, timeout)
    ros.spin_for(0.5)
    out, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    return got, arrival, json.loads(out.strip().splitlines()[-1])


def test_replay_feeds_a_subscriber_the_recorded_messages(ros):
    ep = read_episode(BAG)
    proc = replay("--rate", "4", "--wait-subscribers", "15")
    got, arrival, summary = collect(ros, proc, list(TOPICS))
    for topic in TOPICS:
        recorded = ep[topic].messages
        assert len(got[topic]) == len(recorded) == summary["published"][topic], topic
        assert_same(recorded, got[topic], topic)  # content and original stamps, field by field
    # paced at 4x the recorded speed: the 8 s episode spans ~2 s
    span = arrival["/voxels"][-1] - arrival["/voxels"][0]
    recorded_span = (ep["/voxels"].log_ns[-1] - ep["/voxels"].log_ns[0]) / 1e9
    assert recorded_span / 4 * 0.8 < span < recorded_span / 4 * 1.5 + 0.3


def test_replay_restamped_to_now_keeps_relative_timing(ros):
    ep = read_episode(BAG)
    t_start = time.time_ns()
    proc = replay(
        "--rate", "8", "--restamp", "--topics", "/voxels", "/franka/command_chunk", "--wait-subscribers", "15"
    )
    got, _arrival, summary = collect(ros, proc, ["/voxels", "/franka/command_chunk"])
    assert summary["restamped"] and set(summary["published"]) == {"/voxels", "/franka/command_chunk"}
    orig = ep["/voxels"].header_ns()
    new = np.array([stamp_to_ns(m.header.stamp) for m in got["/voxels"]])
    offsets = new - orig
    assert np.all(offsets == offsets[0])  # one constant shift
    assert t_start - 60e9 < new[0] < time.time_ns()  # ... to now, not 2023
    chunks = [chunk_from_msg(m) for m in got["/franka/command_chunk"]]
    orig_chunks = [chunk_from_msg(m) for m in ep["/franka/command_chunk"].messages]
    assert chunks[5].times_ns[0] - orig_chunks[5].times_ns[0] == offsets[0]
    np.testing.assert_allclose(chunks[5].poses, orig_chunks[5].poses)


def test_replay_robot_mode_publishes_only_commands_after_checking_the_start(ros):
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    from equidiff_core import geometry
    from equidiff_ros.common import RELIABLE_QOS

    ep = read_episode(BAG)
    first = chunk_from_msg(ep["/franka/command_chunk"].messages[0])
    f = ros.f
    pose_pub = ros.node.create_publisher(f.cls("geometry_msgs/msg/PoseStamped"), "/franka/ee_pose", RELIABLE_QOS)

    def publish_pose(offset):
        p, q = geometry.pos_quat_from_pose(first.poses[0])
        p = p + offset
        pose_pub.publish(
            f.make(
                "geometry_msgs/msg/PoseStamped",
                header=f.header(0, "fr3_link0"),
                pose=f.make(
                    "geometry_msgs/msg/Pose",
                    position=f.make("geometry_msgs/msg/Point", x=p[0], y=p[1], z=p[2]),
                    orientation=f.make("geometry_msgs/msg/Quaternion", x=q[0], y=q[1], z=q[2], w=q[3]),
                ),
            )
        )

    # a (fake) franka node far from the start pose: refused, nothing published
    chunks = []
    # Deep enough for every chunk of the episode: a keep-last-10 reader on a busy machine (the
    # test spins only every 50 ms) lost chunks that replay had delivered.
    every_chunk = QoSProfile(depth=len(ep["/franka/command_chunk"]) + 10, reliability=ReliabilityPolicy.RELIABLE)
    ros.node.create_subscription(
        f.cls(TOPICS["/franka/command_chunk"]),
        "/franka/command_chunk",
        lambda m: chunks.append(chunk_from_msg(m)),
        every_chunk,
    )
    proc = replay("--robot", "--rate", "8")
    ros.spin_until(lambda: proc.poll() is not None or (publish_pose(np.array([0.2, 0, 0])) and False), 60.0, 0.05)
    _out, err = proc.communicate(timeout=30)
    assert proc.returncode == 1 and "cm from the episode's first target" in err
    assert chunks == []

    proc = replay("--robot", "--rate", "8")
    ros.spin_until(lambda: proc.poll() is not None or (publish_pose(np.zeros(3)) and False), 60.0, 0.05)
    out, err = proc.communicate(timeout=30)
    ros.spin_for(0.5)
    assert proc.returncode == 0, err
    summary = json.loads(out.strip().splitlines()[-1])
    assert summary["published"] == {"/franka/command_chunk": len(ep["/franka/command_chunk"])}
    assert len(chunks) == len(ep["/franka/command_chunk"])
    assert abs(chunks[0].stamp_ns - time.time_ns()) < 60e9  # re-stamped for execution now


def test_replay_of_a_broken_bag_fails_clearly(tmp_path):
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "bad.mcap").write_bytes(b"\x89MCAP0\r\n")
    out = subprocess.run(
        [sys.executable, "-m", "equidiff_ros.cli", "replay", str(bad)], capture_output=True, text=True, timeout=60
    )
    assert out.returncode == 1 and "unreadable bag" in out.stderr
