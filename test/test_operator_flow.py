"""The operator flow (issue 16 item 3): `equidiff lab` against live nodes, teleop takeover
marked in the episode, and the policy's enable/pause gate."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from helpers_data import RosHarness, decoded
from helpers_model import export_tiny_baseline
from helpers_ros import spawn_node, stop_node

from equidiff_core import geometry
from equidiff_core.config import default_config_dir, load_lab_config
from equidiff_core.recording import InterventionLog

LAB = load_lab_config(default_config_dir() / "lab.yaml")
S = 1_000_000_000


def lab_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "equidiff_ros.cli", "lab", *args],
        capture_output=True,
        text=True,
        timeout=120,
        env=dict(os.environ, OMP_NUM_THREADS="1"),
    )


def test_intervention_log_lists_each_takeover_from_the_episode_start():
    log = InterventionLog(start_ns=10 * S)
    log.update(False, 10 * S)  # not driving at the start: nothing
    log.update(True, 11 * S)
    log.update(True, 12 * S)  # still the same takeover
    log.update(False, 13 * S + S // 2)
    log.update(True, 20 * S)  # ongoing when the episode ends
    assert log.metadata(end_ns=21 * S) == {"interventions": "1.00-3.50 10.00-11.00", "intervention_count": "2"}
    already = InterventionLog(start_ns=5 * S)
    already.update(True, 4 * S)  # driving before the episode began: counts from its start
    assert already.metadata(end_ns=6 * S)["interventions"] == "0.00-1.00"


@pytest.mark.ros
@pytest.mark.slow
def test_lab_cli_records_an_episode_with_a_teleop_takeover(ros_domain, tmp_path):
    from rosbags.rosbag2 import Reader

    from equidiff_core.bags import read_episode
    from equidiff_ros.common import LATCHED_QOS, RELIABLE_QOS, SENSOR_QOS

    out = tmp_path / "episodes"
    ros = RosHarness()
    recorder = spawn_node("recorder_node", f"output_dir:={out}", "task:=lab", "min_free_gib:=0.0")
    teleop = spawn_node("teleop_node", "source:=joy", "rate_hz:=100.0", "resync_after_s:=0.5")
    try:
        f = ros.f
        pose_pub = ros.node.create_publisher(f.cls("geometry_msgs/msg/PoseStamped"), "/franka/ee_pose", RELIABLE_QOS)
        joy_pub = ros.node.create_publisher(f.cls("sensor_msgs/msg/Joy"), "/spacenav/joy", SENSOR_QOS)
        active: list[bool] = []
        ros.node.create_subscription(
            f.cls("std_msgs/msg/Bool"), "/teleop/active", lambda m: active.append(m.data), LATCHED_QOS
        )
        assert ros.spin_until(lambda: active == [False] and joy_pub.get_subscription_count() > 0, 30.0), stop_node(
            teleop
        )
        p, q = geometry.pos_quat_from_pose(geometry.make_pose(np.diag([1.0, -1, -1]), [0.45, 0.0, 0.2]))
        pose = f.make(
            "geometry_msgs/msg/PoseStamped",
            header=f.header(0, LAB.base_frame),
            pose=f.make(
                "geometry_msgs/msg/Pose",
                position=f.make("geometry_msgs/msg/Point", x=p[0], y=p[1], z=p[2]),
                orientation=f.make("geometry_msgs/msg/Quaternion", x=q[0], y=q[1], z=q[2], w=q[3]),
            ),
        )

        started = lab_cli("record", "start")
        assert started.returncode == 0, started.stderr
        episode = Path(started.stdout.strip())
        assert episode.parent == out

        def drive(axes, seconds):
            end = time.monotonic() + seconds
            while time.monotonic() < end:
                pose_pub.publish(pose)
                joy_pub.publish(
                    f.make(
                        "sensor_msgs/msg/Joy",
                        header=f.header(ros.node.get_clock().now().nanoseconds, ""),
                        axes=[float(a) for a in axes],
                        buttons=[0, 0],
                    )
                )
                ros.spin_for(0.02)

        drive([0.0] * 6, 0.5)  # input inside the deadzone is no takeover
        assert active == [False]
        drive([0.6, 0, 0, 0, 0, 0], 0.6)
        assert ros.spin_until(lambda: active[-1] is True, 10.0), active
        drive([0.0] * 6, 0.2)
        assert ros.spin_until(lambda: active[-1] is False, 10.0), active  # let go: resync_after_s later
        ros.spin_for(0.5)  # the recorder has the edge before the episode is closed

        status = lab_cli("status", "--json")
        assert status.returncode == 0 and f'"recording {episode}"' in status.stdout, status.stdout
        kept = lab_cli("record", "failure")
        assert kept.returncode == 0, kept.stderr
        again = lab_cli("record", "discard")  # nothing to discard now: a clear refusal, exit 1
        assert again.returncode == 1 and "not recording" in again.stderr
    finally:
        logs = stop_node(teleop) + stop_node(recorder)
        ros.close()
    ep = read_episode(episode)
    assert ep.meta.success is False and ep.meta.task == "lab"
    assert ep.meta.extra["intervention_count"] == "1", logs
    start_s, end_s = (float(v) for v in ep.meta.extra["interventions"].split("-"))
    assert 0.4 < start_s < end_s
    with Reader(episode) as reader:
        marks = [
            decoded(raw, conn.msgtype).data for conn, _t, raw in reader.messages() if conn.topic == "/teleop/active"
        ]
    assert marks[-2:] == [True, False]


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    return export_tiny_baseline(tmp_path_factory.mktemp("policy") / "policy.pt")


@pytest.mark.ros
@pytest.mark.slow
def test_policy_publishes_nothing_until_enabled_and_a_takeover_pauses_it(ros_domain, checkpoint, tmp_path):
    import json
    import signal
    import threading

    from std_msgs.msg import Bool, String

    from equidiff_core.pointcloud import grid_to_voxel_msg
    from equidiff_core.twin.processes import start_node, stop_process
    from equidiff_ros.common import LATCHED_QOS, RELIABLE_QOS
    from equidiff_ros.control_client import ControlClient

    lab_path = str(default_config_dir() / "lab.yaml")
    ws = LAB.workspace
    grid = np.zeros((4, ws.resolution, ws.resolution, ws.resolution), np.uint8)
    grid[:, 20:26, 30:36, 2:8] = 200
    stop = threading.Event()
    franka = policy = client = None
    skipped: list[str] = []
    state: list[str] = []
    try:
        franka = start_node("franka_node", {"backend": "dryrun", "lab_config": lab_path}, tmp_path / "franka.log")
        policy = start_node(
            "policy_node",
            {
                "checkpoint": str(checkpoint),
                "lab_config": lab_path,
                "seed": 0,
                "execute_steps": 1,
                "start_paused": True,
            },
            tmp_path / "policy.log",
        )
        client = ControlClient(LAB, lab_path)
        client.node.create_subscription(
            String, "/policy/skipped", lambda m: skipped.append(json.loads(m.data)["reason"]), RELIABLE_QOS
        )
        client.node.create_subscription(String, "/policy/state", lambda m: state.append(m.data), LATCHED_QOS)
        takeover = client.node.create_publisher(Bool, "/teleop/active", LATCHED_QOS)
        client.wait_for(lambda: len(client.data.poses) > 10, 60.0, "/franka/ee_pose from the dry-run arm", franka)

        def feed():
            while not stop.is_set():
                client.pub_voxels.publish(
                    grid_to_voxel_msg(grid, ws.lower, ws.voxel_size, time.time_ns(), LAB.base_frame, client.factory)
                )
                stop.wait(0.2)

        threading.Thread(target=feed, daemon=True).start()
        client.wait_for(lambda: skipped.count("paused") >= 5, 90.0, "'paused' skips while start_paused", policy)
        assert state and state[-1].startswith("paused") and client.data.last_chunk is None
        client.wait_for(lambda: "policy_node" in client.data.diagnostics, 5.0, "policy diagnostics", policy)
        assert client.data.diagnostics["policy_node"]["state"].startswith("paused")

        enabled = lab_cli("policy", "enable")
        assert enabled.returncode == 0 and "running" in enabled.stdout, enabled.stderr
        client.wait_for(lambda: len(client.data.chunks) >= 3, 60.0, "chunks once enabled", policy)
        assert state[-1] == "running"

        takeover.publish(Bool(data=True))  # the operator moves the SpaceMouse
        client.wait_for(lambda: state[-1] == "paused teleop takeover", 10.0, "the takeover pause", policy)
        n = len(client.data.chunks)
        paused_before = skipped.count("paused")
        client.wait_for(lambda: skipped.count("paused") >= paused_before + 5, 30.0, "'paused' skips", policy)
        assert len(client.data.chunks) <= n + 1  # at most one already on the wire
        takeover.publish(Bool(data=False))  # letting go does not resume it
        time.sleep(1.0)
        assert state[-1] == "paused teleop takeover"
        ack = lab_cli("ack")  # franka_node's acknowledgement service answers (nothing was stopped here)
        assert ack.returncode == 0 and "nothing to acknowledge" in ack.stdout, ack.stderr
        home = lab_cli("home")  # the dry-run arm glides home between episodes
        assert home.returncode == 0 and "homing to" in home.stdout, home.stderr
    finally:
        stop.set()
        if client is not None:
            client.close()
        # 30 s: a hang guard only; an inference in flight on a loaded machine finishes first
        codes = [
            stop_process(policy, timeout=30.0, sig=signal.SIGINT),
            stop_process(franka, timeout=30.0, sig=signal.SIGTERM),
        ]
    assert codes == [0, 0], (tmp_path / "policy.log").read_text()[-3000:]


@pytest.mark.ros
@pytest.mark.slow
@pytest.mark.sim
def test_the_operator_flow_drives_the_twin_the_same_way(ros_domain, tmp_path):
    """Issue 16 item 3 in the twin, on simulated time: `equidiff lab` homes the arm, records an
    episode, pauses and resumes the policy; a SpaceMouse takeover pauses it and is marked in the
    bag; the episode is kept as a success. The same commands and nodes as in the lab."""
    import json

    from equidiff_core.bags import read_episode
    from equidiff_core.control import load_control_config
    from equidiff_core.twin.config import TwinConfig
    from equidiff_core.twin.processes import node_command
    from equidiff_core.twin.standin import make_standin_policy
    from equidiff_ros.common import SENSOR_QOS
    from equidiff_ros.twin_supervisor import TwinStack

    cfg_dir = default_config_dir()
    policy = make_standin_policy(tmp_path / "standin.pt", LAB.workspace, preset="tiny", cfg=TwinConfig())
    home = np.array(load_control_config(cfg_dir / "control.yaml").home_position)
    with TwinStack(
        tmp_path / "run",
        cfg_dir / "lab.yaml",
        cfg_dir / "twin.yaml",
        policy=str(policy),
        task="lab",
        domain_id=221 + (ros_domain + 7) % 12,
        log=lambda s: None,
    ) as stack:
        sup = stack.sup
        stack.group.start(
            "teleop_node",
            node_command(
                "teleop_node",
                {"lab_config": str(cfg_dir / "lab.yaml"), "use_sim_time": True, "source": "joy", "resync_after_s": 0.5},
            ),
        )
        f = sup.factory
        joy_pub = sup.node.create_publisher(f.cls("sensor_msgs/msg/Joy"), "/spacenav/joy", SENSOR_QOS)
        sup.wait_for(lambda: joy_pub.get_subscription_count() > 0, 60.0, "teleop_node", stack.check)

        homed = lab_cli("home")
        assert homed.returncode == 0 and "homing" in homed.stdout, homed.stdout + homed.stderr
        sup.wait_for(
            lambda: np.linalg.norm(sup.current()[0][:3, 3] - home) < 0.01, 120.0, "the arm at home", stack.check
        )
        started = lab_cli("record", "start")
        assert started.returncode == 0, started.stderr
        episode = Path(started.stdout.strip())
        sup.open_gate()  # the twin passes the policy's chunks to the arm, as in an episode

        def state() -> dict:
            status = lab_cli("status", "--json")
            assert status.returncode == 0, status.stderr
            return json.loads(status.stdout)

        sup.wait_for(lambda: sup.chunk_arrivals, 60.0, "a policy chunk", stack.check)
        assert lab_cli("policy", "pause").returncode == 0 and state()["policy"].startswith("paused")
        sup.sim_sleep(0.5, stack.check)  # a chunk in flight may still land
        paused_at = len(sup.chunk_arrivals)
        sup.sim_sleep(2.0, stack.check)
        assert len(sup.chunk_arrivals) == paused_at  # paused: no chunk for 2 s of sim time
        assert lab_cli("policy", "resume").returncode == 0
        sup.wait_for(lambda: len(sup.chunk_arrivals) > paused_at, 60.0, "chunks after resuming", stack.check)

        def drive(axes, sim_seconds):  # SpaceMouse reports stamped on the node clock, at ~50 Hz of sim time
            end = sup.now_ns() + int(sim_seconds * S)
            while sup.now_ns() < end:
                joy_pub.publish(
                    f.make(
                        "sensor_msgs/msg/Joy",
                        header=f.header(sup.now_ns(), ""),
                        axes=[float(a) for a in axes],
                        buttons=[0, 0],
                    )
                )
                stack.check()
                time.sleep(0.02)

        drive([0.5, 0, 0, 0, 0, 0], 1.0)
        assert state()["policy"].startswith("paused") and "teleop" in state()["policy"]
        drive([0.0] * 6, 1.0)  # let go: the takeover ends, and the policy stays paused until resumed
        sup.sim_sleep(1.0, stack.check)
        assert state()["policy"].startswith("paused")
        kept = lab_cli("record", "success")
        assert kept.returncode == 0, kept.stderr
        sup.close_gate()
    ep = read_episode(episode)
    assert ep.meta.success is True and ep.meta.task == "lab"
    assert ep.meta.extra["intervention_count"] == "1", ep.meta.extra
    assert ep.message_counts.get("/franka/command_chunk", 0) > 0  # the arm's commands were recorded
    assert ep.message_counts.get("/teleop/active", 0) >= 2  # the takeover's start and end
