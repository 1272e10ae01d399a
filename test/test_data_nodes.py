"""recorder_node and teleop_node as real processes on a private ROS domain."""

from __future__ import annotations

import itertools
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from helpers_data import RosHarness, assert_same, decoded
from helpers_ros import spawn_node, stop_node

from equidiff_core import geometry
from equidiff_core.cameras.color import color_image_msg
from equidiff_core.config import default_config_dir, load_lab_config
from equidiff_core.data.bags import read_episode, repair_bag
from equidiff_core.data.mcap_reader import BagError
from equidiff_core.policy.doubt import ChunkDoubt
from equidiff_core.wire.chunk import PoseChunk, chunk_from_msg, chunk_to_msg
from equidiff_core.wire.pointcloud import grid_to_voxel_msg
from equidiff_core.wire.rosmsg import doubt_msg
from equidiff_core.wire.topics import camera_color_topic

pytestmark = [pytest.mark.ros, pytest.mark.slow]

LAB = load_lab_config(default_config_dir() / "lab.yaml")
IMAGE_TOPIC = camera_color_topic(LAB.cameras[0].name)


@pytest.fixture
def ros(ros_domain):
    h = RosHarness()
    yield h
    h.close()


def make_messages(f, n: int, t0_ns: int):
    """n voxel grids, ee poses, joint states and chunks with distinct content."""
    ws = LAB.workspace
    out = []
    rng = np.random.default_rng(0)
    for i in range(n):
        t = t0_ns + i * 50_000_000
        grid = np.zeros((4, 64, 64, 64), np.uint8)
        idx = rng.integers(0, 64, size=(200 + i, 3))
        grid[:, idx[:, 0], idx[:, 1], idx[:, 2]] = [[255], [i], [2 * i], [3]]
        out.append(("/voxels", grid_to_voxel_msg(grid, ws.lower, ws.voxel_size, t, LAB.base_frame, f)))
        pose = geometry.make_pose(geometry.rotz(0.01 * i) @ np.diag([1.0, -1, -1]), [0.4 + 0.001 * i, 0.0, 0.2])
        p, q = geometry.pos_quat_from_pose(pose)
        out.append(
            (
                "/franka/ee_pose",
                f.make(
                    "geometry_msgs/msg/PoseStamped",
                    header=f.header(t, LAB.base_frame),
                    pose=f.make(
                        "geometry_msgs/msg/Pose",
                        position=f.make("geometry_msgs/msg/Point", x=p[0], y=p[1], z=p[2]),
                        orientation=f.make("geometry_msgs/msg/Quaternion", x=q[0], y=q[1], z=q[2], w=q[3]),
                    ),
                ),
            )
        )
        out.append(
            (
                "/franka/joint_states",
                f.make(
                    "sensor_msgs/msg/JointState",
                    header=f.header(t, ""),
                    name=["fr3_finger_joint1", "fr3_finger_joint2"],
                    position=[0.01 * (i % 4), 0.01 * (i % 4)],
                ),
            )
        )
        chunk = PoseChunk(t, np.array([t + 100_000_000]), pose[None], np.array([0.08]))
        out.append(("/franka/command_chunk", chunk_to_msg(chunk, f, LAB.base_frame)))
        rgb = np.zeros((48, 64, 3), np.uint8)
        rgb[:, : 4 * i] = (200, 30 + i, 30)  # each image distinct
        out.append((IMAGE_TOPIC, color_image_msg(rgb, t, LAB.cameras[0].frame_id, f)))
        out.append(("/policy/doubt", doubt_msg(f, ChunkDoubt(t, 0.001 * i, 0.002 * i))))
    return out


def wait_status(ros: RosHarness, prefix: str, timeout: float = 20.0) -> str:
    from equidiff_ros.common import LATCHED_QOS

    seen = []
    sub = ros.node.create_subscription(
        ros.f.cls("std_msgs/msg/String"), "/recorder/status", lambda m: seen.append(m.data), LATCHED_QOS
    )
    ok = ros.spin_until(lambda: bool(seen) and seen[-1].startswith(prefix), timeout)
    ros.node.destroy_subscription(sub)
    assert ok, f"recorder status never became {prefix!r} (saw {seen})"
    return seen[-1]


def publishers(ros: RosHarness):
    from equidiff_core.wire.topics import TOPIC_RECORDER_COMMAND
    from equidiff_ros.common import RELIABLE_QOS

    types = {
        "/voxels": "sensor_msgs/msg/PointCloud2",
        "/franka/ee_pose": "geometry_msgs/msg/PoseStamped",
        "/franka/joint_states": "sensor_msgs/msg/JointState",
        "/franka/command_chunk": "trajectory_msgs/msg/MultiDOFJointTrajectory",
        IMAGE_TOPIC: "sensor_msgs/msg/CompressedImage",  # recorded by default (record_images)
        "/policy/doubt": "geometry_msgs/msg/Vector3Stamped",
    }
    pubs = {t: ros.node.create_publisher(ros.f.cls(m), t, RELIABLE_QOS) for t, m in types.items()}
    cmd = ros.node.create_publisher(ros.f.cls("std_msgs/msg/String"), TOPIC_RECORDER_COMMAND, RELIABLE_QOS)
    return pubs, cmd


def wait_matched(ros: RosHarness, pubs, timeout=20.0):
    assert ros.spin_until(lambda: all(p.get_subscription_count() > 0 for p in pubs), timeout), (
        "recorder_node never subscribed"
    )


def test_recorder_episode_reads_back_identically(ros, tmp_path):
    from rosbags.rosbag2 import Reader

    out = tmp_path / "episodes"
    proc = spawn_node("recorder_node", f"output_dir:={out}", "task:=stack", "operator:=tester", "min_free_gib:=0.0")
    try:
        pubs, cmd = publishers(ros)
        wait_matched(ros, list(pubs.values()) + [cmd])
        wait_status(ros, "idle")
        cmd.publish(ros.f.make("std_msgs/msg/String", data="start"))
        status = wait_status(ros, "recording")
        path = Path(status.split(" ", 1)[1])
        assert path.parent == out and path.name == "stack_0000"
        msgs = make_messages(ros.f, 12, 1_800_000_000 * 10**9)
        for topic, msg in msgs:
            pubs[topic].publish(msg)
            ros.spin_for(0.01)
        bad = doubt_msg(ros.f, ChunkDoubt(1, 0.01, 0.01))
        bad.vector.y = -1.0  # a negative doubt: refused, not recorded (the 12 good ones are)
        pubs["/policy/doubt"].publish(bad)
        ros.spin_for(1.0)
        cmd.publish(ros.f.make("std_msgs/msg/String", data="stop failure slipped at the end"))
        wait_status(ros, "idle")
    finally:
        log = stop_node(proc)
    assert proc.returncode == 0, log

    # Independent reader: rosbags' own Reader and CDR decoder against the rclpy messages published.
    expected: dict[str, list] = {}
    for topic, msg in msgs:
        expected.setdefault(topic, []).append(msg)
    with Reader(path) as reader:
        got: dict[str, list] = {}
        for conn, _ts, raw in reader.messages():
            got.setdefault(conn.topic, []).append(decoded(raw, conn.msgtype))
    for topic, data in expected.items():
        assert len(got.get(topic, [])) == len(data), f"{topic}: {len(got.get(topic, []))} recorded vs {len(data)}"
        assert_same(got[topic], data, topic)
    assert len(got["/tf_static"]) == 1
    info = yaml.safe_load((path / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert info["storage_identifier"] == "mcap" and info["relative_file_paths"] == ["stack_0000.mcap"]
    ep = read_episode(path)
    assert ep.meta.task == "stack" and ep.meta.operator == "tester"
    assert ep.meta.success is False and ep.meta.notes == "slipped at the end"
    assert [t.child_frame_id for t in ep["/tf_static"].messages[0].transforms] == [c.frame_id for c in LAB.cameras]
    chunks_back = [chunk_from_msg(m) for m in ep["/franka/command_chunk"].messages]
    voxels_sent = [m for topic, m in msgs if topic == "/voxels"]  # chunk i answers grid i, 100 ms on
    stamp_ns = lambda m: m.header.stamp.sec * 10**9 + m.header.stamp.nanosec
    assert len(chunks_back) == 12 and chunks_back[3].times_ns[0] == stamp_ns(voxels_sent[3]) + 100_000_000

    # Never overwrite: the next episode of the same task gets the next index. This time the
    # episode is driven by the std_srvs/Trigger services; discard removes it.
    proc = spawn_node("recorder_node", f"output_dir:={out}", "task:=stack", "min_free_gib:=0.0")
    try:
        Trigger = ros.f.cls("std_srvs/srv/Trigger")
        clients = {name: ros.node.create_client(Trigger, f"/recorder/{name}") for name in ("start", "discard", "stop")}
        assert ros.spin_until(lambda: all(c.service_is_ready() for c in clients.values()), 20.0), stop_node(proc)

        def call(name, attempts=1):
            """A request sent right after discovery can lose its reply on a loaded machine: DDS
            matches the reply path on its own (CI: /recorder/start unanswered for 10 s after
            service_is_ready). Calls that change nothing are retried, and they give discovery
            time to finish before the one that changes something (start)."""
            for attempt in range(1, attempts + 1):
                future = clients[name].call_async(Trigger.Request())
                if ros.spin_until(future.done, 10.0 if attempt == attempts else 3.0):
                    return future.result()
            raise AssertionError(f"/recorder/{name} did not answer")

        for name in ("stop", "discard"):  # idle: both refused, nothing changes
            res = call(name, attempts=4)
            assert res.success is False and "not recording" in res.message, res.message
        res = call("start")
        assert res.success and res.message.endswith("stack_0001"), res.message
        second = Path(res.message)
        assert call("start").success is False  # already recording: refused, explained
        res = call("discard")
        assert res.success and "discarded" in res.message
        res = call("stop")
        assert res.success is False and "not recording" in res.message
    finally:
        stop_node(proc)
    assert not second.exists() and path.exists()


def test_sigkilled_recorder_bag_is_recovered(ros, tmp_path):

    out = tmp_path / "episodes"
    proc = spawn_node(
        "recorder_node",
        f"output_dir:={out}",
        "task:=kill",
        "min_free_gib:=0.0",
        "chunk_size_mib:=2.0",
        "chunk_max_age_s:=0.3",
        "autostart:=true",
    )
    try:
        pubs, _cmd = publishers(ros)
        wait_matched(ros, list(pubs.values()))
        path = Path(wait_status(ros, "recording").split(" ", 1)[1])
        msgs = [m for m in make_messages(ros.f, 30, 1_800_000_000 * 10**9) if m[0] == "/voxels"]
        for _topic, msg in msgs:
            pubs["/voxels"].publish(msg)
            ros.spin_for(0.05)
        ros.spin_for(1.5)  # let at least one chunk age out and flush
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
    finally:
        stop_node(proc)
    assert not (path / "metadata.yaml").exists()
    with pytest.raises(BagError, match="bags repair"):
        read_episode(path)
    report = repair_bag(path)
    assert report is not None and report.original is not None and report.original.exists()
    ep = read_episode(path)
    from rosbags.rosbag2 import Reader

    cloud = "sensor_msgs/msg/PointCloud2"
    with Reader(path) as reader:
        recovered = [decoded(raw, cloud) for conn, _t, raw in reader.messages() if conn.topic == "/voxels"]
    published = [m for _t, m in msgs]
    # Everything up to the last completed chunk: a non-empty prefix of what was published.
    assert 0 < len(recovered) <= len(published)
    assert_same(recovered, published[: len(recovered)], "/voxels")
    assert len(recovered) == len(published), "all voxels were flushed (chunk_max_age_s) before the kill"
    assert "recovered by equidiff bags repair" in ep.meta.notes and ep.meta.task == "kill"
    assert report.messages["/voxels"] == len(recovered)


def test_teleop_node_drives_target_from_joy(ros):
    from equidiff_ros.common import RELIABLE_QOS, SENSOR_QOS

    proc = spawn_node(
        "teleop_node",
        "source:=joy",
        "deadzone:=0.1",
        "linear_scale:=[0.1, 0.1, 0.1]",
        "gripper_mode:=buttons",
        "rate_hz:=100.0",
        "publish_hz:=20.0",
    )
    chunks = []
    try:
        f = ros.f
        pose_pub = ros.node.create_publisher(f.cls("geometry_msgs/msg/PoseStamped"), "/franka/ee_pose", RELIABLE_QOS)
        joy_pub = ros.node.create_publisher(f.cls("sensor_msgs/msg/Joy"), "/spacenav/joy", SENSOR_QOS)
        ros.node.create_subscription(
            f.cls("trajectory_msgs/msg/MultiDOFJointTrajectory"),
            "/franka/command_chunk",
            lambda m: chunks.append(chunk_from_msg(m)),
            RELIABLE_QOS,
        )
        assert ros.spin_until(
            lambda: pose_pub.get_subscription_count() > 0 and joy_pub.get_subscription_count() > 0, 20.0
        ), stop_node(proc)
        start = geometry.make_pose(np.diag([1.0, -1, -1]), [0.45, 0.0, 0.2])
        p, q = geometry.pos_quat_from_pose(start)

        def pose_msg():
            return f.make(
                "geometry_msgs/msg/PoseStamped",
                header=f.header(0, LAB.base_frame),
                pose=f.make(
                    "geometry_msgs/msg/Pose",
                    position=f.make("geometry_msgs/msg/Point", x=p[0], y=p[1], z=p[2]),
                    orientation=f.make("geometry_msgs/msg/Quaternion", x=q[0], y=q[1], z=q[2], w=q[3]),
                ),
            )

        def joy(axes, buttons=(0, 0), age_s=0.0):
            stamp = ros.node.get_clock().now().nanoseconds - int(age_s * 1e9)  # as the spacenav driver stamps
            return f.make(
                "sensor_msgs/msg/Joy", header=f.header(stamp, ""), axes=[float(a) for a in axes], buttons=list(buttons)
            )

        # idle input: no commands
        for _ in range(20):
            pose_pub.publish(pose_msg())
            joy_pub.publish(joy([0.05, 0, 0, 0, 0, 0]))
            ros.spin_for(0.02)
        # full deflection, but reported 0.3 s ago (> input_timeout_s 0.2): stale, the arm holds
        for _ in range(20):
            pose_pub.publish(pose_msg())
            joy_pub.publish(joy([1.0, 0, 0, 0, 0, 0], age_s=0.3))
            ros.spin_for(0.02)
        assert chunks == []
        # push +x (and press "close") until the target is 2 cm ahead (0.2 s at 0.1 m/s on a quiet
        # machine; a loaded one delivers some reports after input_timeout_s, which then move
        # nothing), then 1 s more: the lead stays capped at max_lead_m
        t0 = time.monotonic()
        pushed_until = None
        while time.monotonic() - t0 < 60.0 and (pushed_until is None or time.monotonic() < pushed_until):
            pose_pub.publish(pose_msg())
            joy_pub.publish(joy([1.0, 0, 0, 0, 0, 0], (0, 1)))
            ros.spin_for(0.02)
            if pushed_until is None and len(chunks) >= 5 and chunks[-1].poses[0, 0, 3] - 0.45 > 0.02:
                pushed_until = time.monotonic() + 1.0
        ros.spin_for(0.3)
    finally:
        log = stop_node(proc)
    assert len(chunks) >= 5, log
    last = chunks[-1]
    assert len(last) == 1 and last.times_ns[0] > last.stamp_ns  # one point, reached shortly after
    dx = last.poses[0, 0, 3] - 0.45
    # it moves +x but never more than max_lead_m (0.05) ahead of the (static) measured pose
    assert 0.02 < dx <= 0.05 + 1e-6
    assert abs(last.poses[0, 1, 3]) < 1e-6 and abs(last.poses[0, 2, 3] - 0.2) < 1e-6
    np.testing.assert_allclose(last.poses[0, :3, :3], start[:3, :3], atol=1e-6)
    assert last.widths[0] == 0.0  # close button
    xs = [c.poses[0, 0, 3] for c in chunks]
    assert all(b >= a - 1e-9 for a, b in itertools.pairwise(xs))


def test_teleop_node_without_device_names_what_it_looked_for(ros_domain):
    proc = spawn_node("teleop_node", "source:=spacemouse")
    try:
        proc.wait(timeout=30)
    finally:
        log = stop_node(proc)
    assert proc.returncode == 1
    assert "SpaceMouse" in log and ("3Dconnexion" in log or "HID" in log)


def test_recorder_keyboard_mode(ros, tmp_path):
    """keyboard:=true on a terminal: s starts, f keeps the episode as a failure."""
    import pty

    out = tmp_path / "episodes"
    master, slave = pty.openpty()
    args = [
        sys.executable,
        "-m",
        "equidiff_ros.recorder_node",
        "--ros-args",
        "-p",
        f"output_dir:={out}",
        "-p",
        "task:=keys",
        "-p",
        "min_free_gib:=0.0",
        "-p",
        "keyboard:=true",
    ]
    proc = subprocess.Popen(
        args,
        stdin=slave,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=dict(os.environ, OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1"),
    )
    os.close(slave)
    try:
        wait_status(ros, "idle")
        os.write(master, b"s\n")
        path = Path(wait_status(ros, "recording").split(" ", 1)[1])
        os.write(master, b"f\n")
        wait_status(ros, "idle")
    finally:
        stop_node(proc)
        os.close(master)
    assert path.name == "keys_0000"
    meta = read_episode(path).meta
    assert meta.task == "keys" and meta.success is False
