"""`equidiff viz` against real topics: a separate process subscribes, this test publishes, the .rrd is read back."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rerun")
rclpy = pytest.importorskip("rclpy")

from test_viz import (
    LAB,
    T0_NS,
    chunk_msg,
    diagnostics_msg,
    joint_state_msg,
    pose_msg,
    tcp_pose,
    voxel_msg,
)

from equidiff_core.cameras.color import color_image_msg
from equidiff_core.viz.rrd import summarize_rrd
from equidiff_core.wire.rosmsg import RclpyFactory
from equidiff_core.wire.topics import camera_color_topic

N_FRAMES = 8


def _wait_for(predicate, timeout_s: float, what: str, proc: subprocess.Popen | None = None) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return
        if proc is not None and proc.poll() is not None:
            raise AssertionError(
                f"viz exited early ({proc.returncode}) while waiting for {what}:\n{proc.stdout.read()}"
            )
        time.sleep(0.1)
    raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")


@pytest.mark.ros
@pytest.mark.slow
def test_live_viz_logs_real_topics_to_a_readable_rrd(ros_domain, tmp_path):
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import PoseStamped
    from sensor_msgs.msg import CompressedImage, JointState, PointCloud2
    from trajectory_msgs.msg import MultiDOFJointTrajectory

    from equidiff_core.wire.topics import (
        TOPIC_COMMAND_CHUNK,
        TOPIC_DIAGNOSTICS,
        TOPIC_EE_POSE,
        TOPIC_EXECUTED_TARGET,
        TOPIC_JOINT_STATES,
        TOPIC_VOXELS,
    )
    from equidiff_ros.common import RELIABLE_QOS, SENSOR_QOS, VOXEL_QOS

    out = tmp_path / "live.rrd"
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1")
    proc = subprocess.Popen(
        [sys.executable, "-m", "equidiff_ros.cli", "viz", "-o", str(out), "--duration", "120"],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=env,
    )
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = rclpy.create_node("viz_test_publisher", context=ctx)
    try:
        f = RclpyFactory()
        pubs = {
            TOPIC_VOXELS: node.create_publisher(PointCloud2, TOPIC_VOXELS, VOXEL_QOS),
            TOPIC_EE_POSE: node.create_publisher(PoseStamped, TOPIC_EE_POSE, RELIABLE_QOS),
            TOPIC_JOINT_STATES: node.create_publisher(JointState, TOPIC_JOINT_STATES, SENSOR_QOS),
            TOPIC_COMMAND_CHUNK: node.create_publisher(MultiDOFJointTrajectory, TOPIC_COMMAND_CHUNK, RELIABLE_QOS),
            TOPIC_EXECUTED_TARGET: node.create_publisher(PoseStamped, TOPIC_EXECUTED_TARGET, RELIABLE_QOS),
            TOPIC_DIAGNOSTICS: node.create_publisher(DiagnosticArray, TOPIC_DIAGNOSTICS, RELIABLE_QOS),
            "image": node.create_publisher(CompressedImage, camera_color_topic(LAB.cameras[0].name), RELIABLE_QOS),
        }
        rgb = np.zeros((48, 64, 3), np.uint8)
        rgb[:, :32] = (200, 40, 40)
        _wait_for(lambda: all(p.get_subscription_count() > 0 for p in pubs.values()), 60, "viz subscriptions", proc)
        time.sleep(0.5)  # let discovery settle in both directions before the reliable topics count
        for i in range(N_FRAMES):
            t = T0_NS + i * 200_000_000
            pubs[TOPIC_VOXELS].publish(voxel_msg(500 + i, t, f, seed=i))
            pubs[TOPIC_COMMAND_CHUNK].publish(chunk_msg(i * 0.2, t, f))
            pubs[TOPIC_DIAGNOSTICS].publish(diagnostics_msg(100.0 + i, t, f))
            pubs["image"].publish(color_image_msg(rgb, t, LAB.cameras[0].frame_id, f))
            for k in range(4):  # 20 Hz state: exactly the default ee_hz, so no throttling by message time
                ts = t + k * 50_000_000
                pubs[TOPIC_EE_POSE].publish(pose_msg(tcp_pose(ts / 1e9), ts, f))
                pubs[TOPIC_EXECUTED_TARGET].publish(pose_msg(tcp_pose(ts / 1e9 + 0.1), ts, f))
                pubs[TOPIC_JOINT_STATES].publish(joint_state_msg(0.05, ts, f))
                time.sleep(0.05)
        time.sleep(1.5)  # delivery
        proc.send_signal(signal.SIGTERM)  # the way a launch file / systemd stops it
        output, _ = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        node.destroy_node()
        rclpy.shutdown(context=ctx)
    assert proc.returncode == 0, output
    assert f"wrote {out}" in output, output

    s = summarize_rrd(out, count_instances=("Boxes3D:centers",))
    assert s.has_blueprint
    voxels = s["world/voxels"]
    assert voxels.instances["Boxes3D:centers"] == [500 + i for i in range(N_FRAMES)]  # reliable: every frame
    assert voxels.time_range_ns("ros_time") == (T0_NS, T0_NS + (N_FRAMES - 1) * 200_000_000)  # header stamps
    assert s["world/chunk/path"].rows == N_FRAMES
    assert s["metrics/latency/inference"].rows == N_FRAMES
    assert s["world/executed_target"].rows == 4 * N_FRAMES
    assert 0 < s["world/ee"].rows <= 4 * N_FRAMES  # best-effort subscription
    assert s["metrics/gripper_width/measured"].rows > 0
    # arrival minus a stamp from 2023: the age series is computed on the live clock
    age = s["metrics/observation_age/voxels_on_arrival"]
    assert age.rows == N_FRAMES
    for cam in LAB.cameras:
        assert "Transform3D:translation" in s[f"world/cameras/{cam.name}"].static_components  # lab.yaml
    assert 0 < s[f"images/{LAB.cameras[0].name}"].rows <= N_FRAMES  # the camera's JPEG, as published


@pytest.mark.ros
def test_live_viz_refuses_to_spawn_without_a_display(ros_domain, monkeypatch, capsys):
    from equidiff_ros.cli import main

    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    if sys.platform == "darwin":
        pytest.skip("macOS always has a display")
    assert main(["viz"]) == 2
    assert "-o FILE.rrd" in capsys.readouterr().err


def test_viz_command_help_lists_the_three_sinks():
    out = subprocess.run(
        [sys.executable, "-m", "equidiff_ros.cli", "viz", "--help"],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=Path(__file__).resolve().parents[1],
    )
    assert out.returncode == 0, out.stderr
    for flag in ("--spawn", "--connect", "--output", "--per-episode", "--clouds"):
        assert flag in out.stdout
