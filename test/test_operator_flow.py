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
from helpers_ros import spawn_node, stop_node

from equidiff_core import geometry
from equidiff_core.config import default_config_dir, load_lab_config
from equidiff_core.recording import InterventionLog

LAB = load_lab_config(default_config_dir() / "lab.yaml")
S = 1_000_000_000


def lab_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "equidiff_ros.cli", "lab", *args], capture_output=True, text=True,
                          timeout=120, env=dict(os.environ, OMP_NUM_THREADS="1"))


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
        ros.node.create_subscription(f.cls("std_msgs/msg/Bool"), "/teleop/active", lambda m: active.append(m.data),
                                     LATCHED_QOS)
        assert ros.spin_until(lambda: active == [False] and joy_pub.get_subscription_count() > 0, 30.0), \
            stop_node(teleop)
        p, q = geometry.pos_quat_from_pose(geometry.make_pose(np.diag([1.0, -1, -1]), [0.45, 0.0, 0.2]))
        pose = f.make("geometry_msgs/msg/PoseStamped", header=f.header(0, LAB.base_frame),
                      pose=f.make("geometry_msgs/msg/Pose", position=f.make("geometry_msgs/msg/Point", x=p[0], y=p[1],
                                                                            z=p[2]),
                                  orientation=f.make("geometry_msgs/msg/Quaternion", x=q[0], y=q[1], z=q[2], w=q[3])))

        started = lab_cli("record", "start")
        assert started.returncode == 0, started.stderr
        episode = Path(started.stdout.strip())
        assert episode.parent == out

        def drive(axes, seconds):
            end = time.monotonic() + seconds
            while time.monotonic() < end:
                pose_pub.publish(pose)
                joy_pub.publish(f.make("sensor_msgs/msg/Joy", header=f.header(ros.node.get_clock().now().nanoseconds,
                                                                              ""),
                                       axes=[float(a) for a in axes], buttons=[0, 0]))
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
        marks = [decoded(raw, conn.msgtype).data for conn, _t, raw in reader.messages() if conn.topic == "/teleop/active"]
    assert marks[-2:] == [True, False]
