"""Every kind of bad message at the live nodes: each is dropped and counted with its reason on
/diagnostics, the node stays up and acts on the next good message (docs/architecture.md, "What a
node refuses"). One process per node, all four on one private ROS domain."""

from __future__ import annotations

import time

import numpy as np
import pytest

pytest.importorskip("rclpy")

from helpers_bad_messages import (
    DAY_NS,
    bad_chunks,
    bad_clouds,
    bad_ee_poses,
    bad_joint_states,
    bad_voxel_msgs,
    hold_chunk,
    robot_state,
    voxel_msg,
)
from test_policy_node import checkpoint  # noqa: F401 - the module's fixture: a tiny exported policy

from equidiff_core.config import default_config_dir, load_lab_config
from equidiff_core.wire.chunk import chunk_to_msg
from equidiff_core.wire.pointcloud import VoxelGridSpec, cloud_to_msg, voxel_msg_to_grid
from equidiff_core.wire.rosmsg import gripper_width_from_joint_state, joint_state, pose_from_msg, pose_stamped

LAB_PATH = default_config_dir() / "lab.yaml"


def _count(client, node: str, key: str) -> int:
    return int(float(client.data.diagnostics.get(node, {}).get(key, 0)))


def _keep_publishing(publish, done, timeout_s: float, period_s: float = 0.3) -> None:
    """Publish every ``period_s`` until ``done()`` (best-effort readers may lose a burst) or the timeout."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end and not done():
        publish()
        time.sleep(period_s)


@pytest.mark.ros
@pytest.mark.slow
def test_bad_messages_are_dropped_counted_and_the_nodes_go_on(ros_domain, checkpoint, tmp_path):  # noqa: F811
    from geometry_msgs.msg import PoseStamped
    from sensor_msgs.msg import JointState

    from equidiff_core.data.bags import read_episode
    from equidiff_core.twin.processes import start_node, stop_process
    from equidiff_core.wire.topics import TOPIC_EE_POSE, TOPIC_JOINT_STATES
    from equidiff_ros.common import RELIABLE_QOS, SENSOR_QOS
    from equidiff_ros.control_client import ControlClient

    lab = load_lab_config(LAB_PATH)
    ws, frame = lab.workspace, lab.base_frame
    grid = np.zeros((4, ws.resolution, ws.resolution, ws.resolution), np.uint8)
    grid[:, 20:26, 30:36, 2:8] = 200
    grid[0][grid[0] > 0] = 255
    rng = np.random.default_rng(0)
    points = (ws.lower + rng.random((400, 3)) * ws.edge).astype(np.float32)  # base frame = camera frame: lands anywhere
    colors = rng.integers(0, 256, (400, 3), dtype=np.uint8)
    logs = {name: tmp_path / f"{name}.log" for name in ("franka", "policy", "voxel", "recorder")}
    base = {"lab_config": str(LAB_PATH)}
    procs, client = {}, None
    try:
        procs["franka"] = start_node("franka_node", {**base, "backend": "dryrun"}, logs["franka"])
        procs["voxel"] = start_node("voxel_node", {**base, "stale_after_s": 5.0}, logs["voxel"])
        procs["recorder"] = start_node(
            "recorder_node",
            {**base, "output_dir": str(tmp_path / "bags"), "autostart": True, "min_free_gib": 0.0},
            logs["recorder"],
        )
        procs["policy"] = start_node(
            "policy_node",
            {**base, "checkpoint": str(checkpoint), "seed": 0, "execute_steps": 1, "latency_s": -1.0},
            logs["policy"],
        )
        client = ControlClient(lab, str(LAB_PATH))
        f = client.factory
        cloud_pubs = {
            cam.name: client.node.create_publisher(type(cloud_to_msg(points, colors, 0, "", f)), cam.topic, SENSOR_QOS)
            for cam in lab.cameras
        }
        client.wait_for(
            lambda: len(client.data.poses) > 10, 90.0, "/franka/ee_pose from the dry-run arm", procs["franka"]
        )
        here = client.latest_position()

        def dead() -> list[str]:
            return [name for name, proc in procs.items() if proc.poll() is not None]

        # --- voxel_node: bad clouds from one camera among good sets from all three
        def publish_clouds():
            now = time.time_ns()
            front = lab.cameras[0]
            for bad in bad_clouds(f, points, colors, now, front.frame_id).values():
                cloud_pubs[front.name].publish(bad)
            cloud_pubs[front.name].publish(cloud_to_msg(points, colors, now + DAY_NS, front.frame_id, f))
            for cam in lab.cameras:
                cloud_pubs[cam.name].publish(cloud_to_msg(points, colors, now, cam.frame_id, f))

        voxel_reasons = ("dropped_layout", "dropped_frame", "dropped_nan", "dropped_future")
        _keep_publishing(
            publish_clouds,
            lambda: (
                all(_count(client, "voxel_node", k) >= 1 for k in voxel_reasons)
                and _count(client, "voxel_node", "published") >= 1
            ),
            90.0,
        )
        assert all(_count(client, "voxel_node", k) >= 1 for k in voxel_reasons), client.data.diagnostics.get(
            "voxel_node"
        )
        assert _count(client, "voxel_node", "published") >= 1, client.data.diagnostics.get("voxel_node")
        assert not dead(), dead()

        # --- policy_node and recorder_node: bad grids on /voxels among good ones; the policy answers a good one
        sent_good: set[float] = set()

        def publish_grids():
            now = time.time_ns()
            for bad in bad_voxel_msgs(f, grid, ws, now, frame).values():
                client.pub_voxels.publish(bad)
            client.pub_voxels.publish(voxel_msg(f, grid, ws, now + DAY_NS, frame))
            client.pub_voxels.publish(voxel_msg(f, grid, ws, now + 1, frame))
            sent_good.add((now + 1) / 1e9)

        def policy_done() -> bool:
            answered = any(s in sent_good for _, s in client.data.chunks)
            return (
                answered
                and _count(client, "policy_node", "skipped_malformed_observation") >= 1
                and _count(client, "policy_node", "skipped_future_observation") >= 1
            )

        _keep_publishing(publish_grids, policy_done, 120.0)
        assert policy_done(), (
            client.data.diagnostics.get("policy_node"),
            (tmp_path / "policy.log").read_text()[-2000:],
        )
        for key in ("voxels_grid", "voxels_layout", "voxels_frame"):
            client.wait_for(
                lambda k=key: _count(client, "recorder_node", f"dropped_{k}") >= 1,
                30.0,
                f"recorder_node dropping a {key} message",
            )

        # --- policy_node and recorder_node: bad robot state among franka_node's good one; the policy
        # still answers grids sent with it (on franka_node's states), the recorder keeps none of it
        pub_pose = client.node.create_publisher(PoseStamped, TOPIC_EE_POSE, RELIABLE_QOS)
        pub_joints = client.node.create_publisher(JointState, TOPIC_JOINT_STATES, RELIABLE_QOS)
        state = robot_state(here)
        sent_with_bad_state: set[float] = set()

        def publish_states():
            now = time.time_ns()
            for bad in bad_ee_poses(f, state.ee_pose, now, frame).values():
                pub_pose.publish(bad)
            pub_pose.publish(pose_stamped(f, state.ee_pose, now + DAY_NS, frame))
            for bad in bad_joint_states(f, state, now).values():
                pub_joints.publish(bad)
            pub_joints.publish(joint_state(f, state, now + DAY_NS))
            client.pub_voxels.publish(voxel_msg(f, grid, ws, now + 1, frame))
            sent_with_bad_state.add((now + 1) / 1e9)

        policy_drops = [f"dropped_ee_pose_{r}" for r in ("frame", "nan", "quaternion", "future")]
        policy_drops += [f"dropped_joint_states_{r}" for r in ("malformed", "nan", "range", "future")]
        recorder_drops = [f"dropped_franka_ee_pose_{r}" for r in ("frame", "nan", "quaternion")]
        recorder_drops += [f"dropped_franka_joint_states_{r}" for r in ("malformed", "nan", "range")]

        def state_done() -> bool:
            return (
                all(_count(client, "policy_node", k) >= 1 for k in policy_drops)
                and all(_count(client, "recorder_node", k) >= 1 for k in recorder_drops)
                and any(s in sent_with_bad_state for _, s in client.data.chunks)
            )

        _keep_publishing(publish_states, state_done, 120.0)
        assert state_done(), (
            client.data.diagnostics.get("policy_node"),
            client.data.diagnostics.get("recorder_node"),
            (tmp_path / "policy.log").read_text()[-2000:],
        )
        assert not dead(), dead()

        # --- franka_node (and the recorder): bad chunks, then a good one it accepts
        def publish_chunks():
            now = time.time_ns()
            for bad in bad_chunks(f, here, now, frame).values():
                client.pub_chunk.publish(bad)

        franka_reasons = ("malformed_rejected", "nan_rejected", "future_rejected")
        _keep_publishing(
            publish_chunks, lambda: all(_count(client, "franka_node", k) >= 2 for k in franka_reasons), 60.0
        )
        assert all(_count(client, "franka_node", k) >= 2 for k in franka_reasons), client.data.diagnostics.get(
            "franka_node"
        )
        accepted = _count(client, "franka_node", "accepted_chunks")
        target = np.asarray(here) + [0.0, 0.0, 0.01]
        _keep_publishing(
            lambda: client.pub_chunk.publish(chunk_to_msg(hold_chunk(target, time.time_ns()), f, frame)),
            lambda: _count(client, "franka_node", "accepted_chunks") > accepted,
            30.0,
            period_s=1.0,
        )
        assert _count(client, "franka_node", "accepted_chunks") > accepted, client.data.diagnostics.get("franka_node")
        for key in ("franka_command_chunk_nan", "franka_command_chunk_malformed"):
            client.wait_for(
                lambda k=key: _count(client, "recorder_node", f"dropped_{k}") >= 1,
                30.0,
                f"recorder_node dropping a {key} message",
            )
        assert not dead(), dead()
    finally:
        if client is not None:
            client.close()
        codes = {name: stop_process(proc, timeout=30.0) for name, proc in procs.items()}
    assert set(codes.values()) == {0}, (codes, {n: p.read_text()[-1500:] for n, p in logs.items()})
    # the recorder kept the good messages and none of the bad: every grid in the bag is lab.yaml's
    (bag,) = sorted((tmp_path / "bags").iterdir())
    episode = read_episode(bag, topics=("/voxels", "/franka/ee_pose", "/franka/joint_states"))
    spec = VoxelGridSpec.of(ws, frame)
    assert len(episode["/voxels"].messages) >= 1
    for msg in episode["/voxels"].messages:
        voxel_msg_to_grid(msg, spec)
    assert len(episode["/franka/ee_pose"].messages) >= 1 and len(episode["/franka/joint_states"].messages) >= 1
    for msg in episode["/franka/ee_pose"].messages:
        pose_from_msg(msg, frame)
    for msg in episode["/franka/joint_states"].messages:
        assert gripper_width_from_joint_state(msg) is not None
