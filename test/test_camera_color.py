"""camera_node publishes each camera's colour image beside its cloud: a real process, the twin backend
rendering from a shared-memory sim state written by the test, read back with rclpy."""

from __future__ import annotations

import time

import mujoco
import numpy as np
import pytest
from helpers_data import RosHarness
from helpers_ros import spawn_node, stop_node

from equidiff_core.cameras.color import JPEG_FORMAT, image_from_msg
from equidiff_core.cameras.twin import Intrinsics
from equidiff_core.config import default_config_dir, load_lab_config
from equidiff_core.twin import scene
from equidiff_core.twin.config import TwinConfig
from equidiff_core.twin.shared_state import StateWriter
from equidiff_core.wire.pointcloud import msg_to_cloud
from equidiff_core.wire.topics import camera_color_topic

pytestmark = [pytest.mark.ros, pytest.mark.sim, pytest.mark.slow]

LAB = load_lab_config(default_config_dir() / "lab.yaml")
CAM = LAB.cameras[0]


@pytest.fixture
def twin_state():
    cfg = TwinConfig()
    model = scene.build_model(cfg)
    data = mujoco.MjData(model)
    data.qpos[:7] = cfg.sim.initial_q
    scene.apply_scene(model, data, scene.sample_scene(cfg.scene, 3), cfg.scene)
    name = f"equidiff_twin_colortest_{time.time_ns()}"
    writer = StateWriter(len(data.qpos), name)
    writer.write(data.qpos.copy(), 1.0, time.time_ns())
    yield name
    writer.close()


def _listen(ros: RosHarness, publish_color: bool, shm: str, seconds: float):
    from equidiff_ros.common import SENSOR_QOS

    clouds, images = [], []
    ros.node.create_subscription(ros.f.cls("sensor_msgs/msg/PointCloud2"), CAM.topic, clouds.append, SENSOR_QOS)
    image_topic = camera_color_topic(CAM.name)
    ros.node.create_subscription(ros.f.cls("sensor_msgs/msg/CompressedImage"), image_topic, images.append, SENSOR_QOS)
    proc = spawn_node(
        "camera_node",
        "backend:=twin",
        f"camera:={CAM.name}",
        f'backend_options:="{{shm_name: {shm}, width: 106, height: 60}}"',  # a YAML string, as the node reads it
        f"publish_color:={str(publish_color).lower()}",
    )
    try:
        ros.spin_until(lambda: len(clouds) >= 4 or proc.poll() is not None, 60.0)
        ros.spin_for(seconds)
        image_publishers = ros.node.count_publishers(image_topic)
    finally:
        log = stop_node(proc)
    return clouds, images, image_publishers > 0, log


def test_camera_node_publishes_the_colour_image_with_its_clouds_stamp_and_frame(ros_domain, twin_state):
    ros = RosHarness()
    try:
        clouds, images, advertised, log = _listen(ros, True, twin_state, 1.0)
    finally:
        ros.close()
    assert len(clouds) >= 4 and advertised, log
    cloud_stamps = {(m.header.stamp.sec, m.header.stamp.nanosec) for m in clouds}
    image_stamps = [(m.header.stamp.sec, m.header.stamp.nanosec) for m in images]
    assert len(images) >= len(clouds) - 1  # one image per cloud (the newest may still be on the way)
    assert set(image_stamps) <= cloud_stamps | {image_stamps[-1]}  # each image stamped like its cloud
    msg = images[0]
    assert msg.format == JPEG_FORMAT and msg.header.frame_id == CAM.frame_id
    rgb, _ = image_from_msg(msg)
    assert rgb.shape == (60, 106, 3) and rgb.std() > 5  # a rendered scene, not a blank
    # the same frame: each cloud point's colour is the image's pixel it projects to (up to JPEG's few levels)
    cloud = msg_to_cloud(next(m for m in clouds if (m.header.stamp.sec, m.header.stamp.nanosec) == image_stamps[0]))
    intr = Intrinsics.from_fovy(106, 60, TwinConfig().render.fovy_deg)
    u = np.round(cloud.points[:, 0] / cloud.points[:, 2] * intr.fx + intr.cx - 0.5).astype(int)
    v = np.round(cloud.points[:, 1] / cloud.points[:, 2] * intr.fy + intr.cy - 0.5).astype(int)
    assert np.abs(rgb[v, u].astype(int) - cloud.colors).mean() < 6


def test_publish_color_false_publishes_no_image(ros_domain, twin_state):
    ros = RosHarness()
    try:
        clouds, images, advertised, log = _listen(ros, False, twin_state, 0.5)
    finally:
        ros.close()
    assert len(clouds) >= 4, log
    assert images == [] and not advertised
