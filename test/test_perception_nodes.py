"""camera_node and voxel_node as separate processes with real rclpy on a private ROS_DOMAIN_ID."""

import re
import subprocess
import sys
import time

import numpy as np
import pytest
from helpers_ros import spawn_node, stop_node

from equidiff_core.benches.voxelize import synthetic_scene
from equidiff_core.config import default_config_dir, load_lab_config
from equidiff_core.perception.voxels import voxelize_reference

LAB_YAML = str(default_config_dir() / "lab.yaml")


def test_nodes_print_usage_without_starting_ros():
    for node in ("camera_node", "voxel_node"):
        out = subprocess.run(
            [sys.executable, "-m", f"equidiff_ros.{node}", "--help"], capture_output=True, text=True, timeout=60
        )
        assert out.returncode == 0, out.stderr
        assert f"usage: {node}" in out.stdout and "Parameters" in out.stdout


# --- helpers -----------------------------------------------------------------------------


def _spawn(node, *params):
    return spawn_node(node, f"lab_config:={LAB_YAML}", *params)


class RosProbe:
    """An rclpy node in the test process: cloud publishers, /voxels and /diagnostics subscribers."""

    def __init__(self):
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.executors import SingleThreadedExecutor
        from sensor_msgs.msg import PointCloud2

        from equidiff_ros.common import RELIABLE_QOS, SENSOR_QOS, VOXEL_QOS

        self.rclpy = rclpy
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node("perception_tester", context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.lab = load_lab_config(LAB_YAML)
        self.pubs = {c.name: self.node.create_publisher(PointCloud2, c.topic, SENSOR_QOS) for c in self.lab.cameras}
        self.voxels, self.clouds, self.diagnostics = [], [], []
        self.node.create_subscription(PointCloud2, "/voxels", self.voxels.append, VOXEL_QOS)
        self.node.create_subscription(PointCloud2, self.lab.cameras[0].topic, self.clouds.append, SENSOR_QOS)
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self.diagnostics.append, RELIABLE_QOS)

    def publish(self, name, msg):
        self.pubs[name].publish(msg)

    def spin_for(self, seconds):
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.executor.spin_once(timeout_sec=0.02)

    def wait_for(self, predicate, timeout, every=None, period=0.1):
        """Spin until predicate() holds; call every() each period (publishing); True if it held."""
        end = time.monotonic() + timeout
        next_call = 0.0
        while time.monotonic() < end:
            if every is not None and time.monotonic() >= next_call:
                every()
                next_call = time.monotonic() + period
            self.executor.spin_once(timeout_sec=0.02)
            if predicate():
                return True
        return False

    def voxel_status(self):
        for msg in reversed(self.diagnostics):
            for status in msg.status:
                if status.name == "voxel_node":
                    return status.message, {kv.key: kv.value for kv in status.values}
        return None, {}

    def close(self):
        self.executor.shutdown()
        self.node.destroy_node()
        self.rclpy.shutdown(context=self.context)


@pytest.fixture
def tester(ros_domain):
    t = RosProbe()
    yield t
    t.close()


@pytest.fixture(scope="module")
def scene():
    lab = load_lab_config(LAB_YAML)
    clouds = synthetic_scene(lab, 20_000, seed=7)
    exts = [c.extrinsics.matrix() for c in lab.cameras]
    expected = voxelize_reference(clouds, exts, lab.workspace)
    assert expected[0].sum() > 0
    return lab, clouds, expected


def _cloud_msgs(lab, clouds, stamp_ns):
    from equidiff_core.wire.pointcloud import cloud_to_msg
    from equidiff_core.wire.rosmsg import RclpyFactory

    f = RclpyFactory()
    return {c.name: cloud_to_msg(p, col, stamp_ns, c.frame_id, f) for c, (p, col) in zip(lab.cameras, clouds)}


def _grid(msg, lab):
    from equidiff_core.wire.pointcloud import voxel_msg_to_grid

    return voxel_msg_to_grid(msg, lab.workspace.resolution)


# --- voxel_node ---------------------------------------------------------------------------


@pytest.mark.ros
@pytest.mark.slow
def test_three_clouds_become_the_expected_grid_and_a_missing_camera_stops_output(tester, scene):
    lab, clouds, expected = scene
    names = [c.name for c in lab.cameras]
    proc = _spawn("voxel_node", "stale_after_s:=0.6", "slop_s:=0.05", "observation_hz:=5.0")
    stamps = []

    def publish(which=names):
        stamp = time.time_ns()
        stamps.append(stamp)
        for name, msg in _cloud_msgs(lab, clouds, stamp).items():
            if name in which:
                tester.publish(name, msg)

    try:
        # 1. all three cameras -> the exact grid, stamped with a capture stamp, in the base frame
        assert tester.wait_for(lambda: tester.voxels, 25.0, publish), stop_node(proc)
        msg = tester.voxels[-1]
        np.testing.assert_array_equal(_grid(msg, lab), expected)
        stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        assert stamp in stamps and msg.header.frame_id == "fr3_link0"
        # 2. cam_right goes silent -> output stops within stale_after_s, and diagnostics say why
        tester.spin_for(0.3)
        publish(names[:2])
        tester.wait_for(lambda: False, 1.0, lambda: publish(names[:2]))  # let it go stale
        count = len(tester.voxels)
        assert not tester.wait_for(lambda: len(tester.voxels) > count, 2.0, lambda: publish(names[:2]))
        assert tester.wait_for(lambda: "cam_right" in (tester.voxel_status()[0] or ""), 3.0, lambda: publish(names[:2]))
        message, values = tester.voxel_status()
        assert message.startswith("stale") and "cam_right (last cloud" in message
        assert float(values["voxelize_ms"]) > 0 and int(values["published"]) >= 1
        # 3. it comes back -> output resumes (as generous as the first grid: a loaded machine only delays it)
        assert tester.wait_for(lambda: len(tester.voxels) > count, 25.0, publish)
        assert proc.poll() is None
    finally:
        out = stop_node(proc)
    # the log names cam_right the moment it goes stale (a change in the stale set is never throttled)
    assert re.search(r"stale camera\(s\) [^\n]*cam_right \(last cloud", out), out


@pytest.mark.ros
@pytest.mark.slow
def test_a_camera_never_seen_blocks_output_and_malformed_clouds_do_not_crash_the_node(tester, scene):
    from equidiff_core.wire.pointcloud import cloud_to_msg
    from equidiff_core.wire.rosmsg import RclpyFactory

    lab, clouds, expected = scene
    f = RclpyFactory()
    front = lab.cameras[0]
    proc = _spawn("voxel_node", "stale_after_s:=1.0")

    def malformed(stamp):
        good = lambda: cloud_to_msg(clouds[0][0], clouds[0][1], stamp, front.frame_id, f)
        no_z = good()
        no_z.fields = [fl for fl in no_z.fields if fl.name != "z"]
        bad_step = good()
        bad_step.point_step = 12
        nan = cloud_to_msg(np.full((10, 3), np.nan, np.float32), np.zeros((10, 3), np.uint8), stamp, front.frame_id, f)
        empty = cloud_to_msg(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8), stamp, front.frame_id, f)
        wrong_frame = cloud_to_msg(clouds[0][0], clouds[0][1], stamp, "somewhere_else", f)
        return [no_z, bad_step, nan, empty, wrong_frame]

    rounds = [0]

    def publish_malformed_front():
        stamp = time.time_ns()
        msgs = _cloud_msgs(lab, clouds, stamp)
        bad_ones = malformed(stamp)
        rounds[0] += 1  # rotate the order: a best-effort burst may lose its tail, never every kind
        for bad in bad_ones[rounds[0] % 5 :] + bad_ones[: rounds[0] % 5]:
            tester.publish(front.name, bad)
        for name in ("cam_left", "cam_right"):
            tester.publish(name, msgs[name])

    try:
        # only malformed clouds from cam_front: no output, the node keeps running and counts drops
        assert tester.wait_for(
            lambda: int(tester.voxel_status()[1].get("cam_front_dropped", 0)) >= 25, 40.0, publish_malformed_front
        ), stop_node(proc)
        assert not tester.voxels and proc.poll() is None
        assert "cam_front (never received)" in tester.voxel_status()[0]

        # valid clouds from all three (malformed ones still interleaved) -> the exact grid.
        # The valid set goes first: a loaded machine loses the tail of a best-effort burst.
        def publish_all():
            for name, msg in _cloud_msgs(lab, clouds, time.time_ns()).items():
                tester.publish(name, msg)
            publish_malformed_front()

        assert tester.wait_for(lambda: tester.voxels, 30.0, publish_all), stop_node(proc)
        np.testing.assert_array_equal(_grid(tester.voxels[-1], lab), expected)
        assert proc.poll() is None
    finally:
        out = stop_node(proc)
    for reason in ("lacks field(s) ['z']", "NaN", "zero points", "is not 'cam_front_color_optical_frame'"):
        assert reason in out, reason


# --- camera_node ---------------------------------------------------------------------------


@pytest.mark.ros
@pytest.mark.slow
def test_replayed_bag_through_camera_node_and_voxel_node(tester, scene, tmp_path):
    from test_cameras import write_cloud_bag

    lab, clouds, expected = scene
    bag = tmp_path / "episode"
    write_cloud_bag(bag, {c.topic: [cl] * 6 for c, cl in zip(lab.cameras, clouds)}, period_ns=200_000_000)
    camera = _spawn("camera_node", "backend:=replay", f"bag:={bag}", "loop:=true")
    voxel = _spawn("voxel_node", "slop_s:=0.1")
    try:
        assert tester.wait_for(lambda: tester.voxels and tester.clouds, 30.0), stop_node(camera) + stop_node(voxel)
        cloud = tester.clouds[-1]
        assert cloud.header.frame_id == "cam_front_color_optical_frame"
        assert cloud.width == len(clouds[0][0]) and cloud.point_step == 16
        age_s = (time.time_ns() - (cloud.header.stamp.sec * 10**9 + cloud.header.stamp.nanosec)) / 1e9
        assert -0.5 < age_s < 2.0  # restamped: live, not the bag's 2023 stamps
        np.testing.assert_array_equal(_grid(tester.voxels[-1], lab), expected)
        # The replay keeps flowing (looped) and never faster than the bag's 5 Hz; the grids follow,
        # never closer than the observation period allows. Only upper bounds on counts: a loaded
        # machine slows the flow (4 grids in 3 s once on CI), it cannot speed it up.
        clouds_before, voxels_before = len(tester.clouds), len(tester.voxels)
        tester.spin_for(3.0)
        n_clouds, n_voxels = len(tester.clouds) - clouds_before, len(tester.voxels) - voxels_before
        assert 2 <= n_clouds <= 20, n_clouds  # 15 expected (3 cameras at 5 Hz)
        assert 2 <= n_voxels <= 20, n_voxels
        stamps = [v.header.stamp.sec * 10**9 + v.header.stamp.nanosec for v in tester.voxels[voxels_before - 1 :]]
        assert min(np.diff(stamps)) >= 0.75 * 0.2e9, np.diff(stamps)  # voxel_node's rate cap at 5 Hz
        assert camera.poll() is None and voxel.poll() is None
    finally:
        cam_out = stop_node(camera)
        stop_node(voxel)
    assert "tf2_msgs is not installed" in cam_out


@pytest.mark.ros
@pytest.mark.slow
def test_composed_process_runs_one_camera_node_per_camera_each_with_its_name_and_parameters(tester, scene, tmp_path):
    """``equidiff_composed`` with two camera_nodes (``NAME=camera_node``): each is a node of its
    own name and reads its own parameters (its camera) from the parameter file, keyed by that name."""
    import os
    import signal

    from test_cameras import write_cloud_bag

    from equidiff_core.twin.processes import composed_command, stop_process

    lab, clouds, _expected = scene
    bag = tmp_path / "episode"
    write_cloud_bag(bag, {c.topic: [cl] * 6 for c, cl in zip(lab.cameras, clouds)}, period_ns=200_000_000)
    front, left = lab.cameras[0].name, lab.cameras[1].name
    params = {"lab_config": LAB_YAML, "backend": "replay", "bag": str(bag), "loop": True}
    cmd = composed_command(
        {"camera_a": {**params, "camera": front}, "camera_b": {**params, "camera": left}},
        tmp_path / "params.yaml",
        kinds={"camera_a": "camera_node", "camera_b": "camera_node"},
    )
    proc = subprocess.Popen(
        cmd, env=dict(os.environ, OMP_NUM_THREADS="1"), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
    )

    def cameras_reported() -> set[str]:
        return {s.name for msg in tester.diagnostics for s in msg.status if s.name.startswith("camera_node/")}

    try:
        wanted = {f"camera_node/{front}", f"camera_node/{left}"}
        assert tester.wait_for(lambda: cameras_reported() >= wanted, 60.0), cameras_reported()
        # the graph's discovery is asynchronous: the nodes' messages can arrive before their names do
        assert tester.wait_for(lambda: {"camera_a", "camera_b"} <= set(tester.node.get_node_names()), 30.0), (
            tester.node.get_node_names()
        )
        assert cameras_reported() == wanted  # each node its own camera, none all of them
        # the front camera's clouds flow (its diagnostics may come first on a loaded machine)
        assert tester.wait_for(lambda: tester.clouds, 30.0)
    finally:
        stop_process(proc, timeout=10.0, sig=signal.SIGINT)
    assert proc.returncode == 0, proc.stdout.read()


@pytest.mark.ros
def test_camera_node_without_realsense_fails_fast_naming_the_serial(ros_domain):
    proc = _spawn("camera_node", "backend:=realsense", "camera:=cam_left")
    try:
        proc.wait(timeout=60)
    finally:
        out = stop_node(proc)
    assert proc.returncode == 1
    assert "'cam_left' with serial 215122250002 not found" in out


@pytest.mark.ros
@pytest.mark.slow
def test_camera_node_resets_a_stalled_realsense_and_publishes_again(tester, tmp_path, monkeypatch):
    """camera_node (real rclpy, its own process) on a fake pyrealsense2 whose device stalls after 20 frames."""
    import os

    from helpers_realsense import install_in_subprocess

    front = tester.lab.cameras[0]
    fake = install_in_subprocess(tmp_path, [front.serial], stall_after_frames=20, reset_s=1.0)
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([fake, os.environ.get("PYTHONPATH", "")]))
    proc = _spawn("camera_node", "backend:=realsense", f"camera:={front.name}")

    def camera_status():
        for msg in reversed(tester.diagnostics):
            for status in msg.status:
                if status.name == f"camera_node/{front.name}":
                    return status.message, {kv.key: kv.value for kv in status.values}
        return None, {}

    try:
        assert tester.wait_for(lambda: tester.clouds, 60.0), stop_node(proc)
        # 20 frames at 30 fps, then 3 read timeouts of 1 s, a reset, the device back 1 s later
        assert tester.wait_for(lambda: camera_status()[1].get("reconnects") == "1", 60.0), stop_node(proc)
        values = camera_status()[1]
        assert values["resets"] == "1" and values["last_recovery_reason"] == "3 frame timeouts in a row"
        count = len(tester.clouds)
        assert tester.wait_for(lambda: len(tester.clouds) > count + 2, 30.0)  # clouds flow again
        assert len(tester.clouds[-1].data) == 48 * 16  # every pixel of the fake depth image
        assert proc.poll() is None
    finally:
        out = stop_node(proc)
    assert "3 in a row: stream stopped, hardware reset, waiting up to 10.0 s for it to come back" in out
