"""camera_node: coloured point clouds of one configured camera, or of all of them.

Wiring:
  backend (``realsense`` | ``replay`` | ``twin``, built by ``cameras.make_camera``)
      -> one reader thread per camera: ``Camera.read`` -> depth limits (``cameras.limit_depth``)
      -> ``wire.pointcloud.cloud_to_msg`` -> /cameras/<name>/points (sensor-data QoS) at ``publish_hz``
      -> with ``publish_color``: the same frame's colour image as JPEG (``cameras.color``)
         -> /cameras/<name>/color/image_raw/compressed (sensor_msgs/CompressedImage, same stamp,
         frame and QoS as the cloud)
  once at start -> /tf_static (``tf2_msgs/TFMessage``, transient local): base -> each optical
      frame from the configured extrinsics, when tf2_msgs is installed (not on a PyPI-only
      machine: logged once; bags get /tf_static from the recorder)
  timer at 1 Hz -> /diagnostics (``camera_node/<name>``: frames published, read errors, age,
      the backend's hardware resets / reconnects and why the last recovery began, colour images
      published and the mean JPEG encoding time)

A RealSense that stalls (``reset_after_timeouts`` read timeouts in a row) is hardware-reset
and reopened with its options by the backend itself (``RealSenseCamera.read``); meanwhile
each read fails with a line saying what the camera is doing, logged throttled per camera,
and the thread keeps reading, so the node never stops for a camera that went away.

The header stamp is the capture time the backend reports (host clock for RealSense with
global time, the node clock for replay, sim time for the twin); the frame id is
``<name>_color_optical_frame``.

A RealSense that is not connected stops the node at once with the missing serial named.

Parameters: ``PARAMETERS`` below (``--help``, ``ros2 param describe``, docs/parameters.md).
"""

from __future__ import annotations

import sys
import threading
import time

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node
from sensor_msgs.msg import CompressedImage, PointCloud2

from equidiff_core.cameras import (
    BACKENDS,
    CameraError,
    NoFrameYet,
    extrinsics_tf_message,
    limit_depth,
    make_camera,
)
from equidiff_core.cameras.color import DEFAULT_JPEG_QUALITY, ImageError, color_image_msg
from equidiff_core.cameras.replay import ReplayFinished
from equidiff_core.config import Bounds, ConfigError, parse_yaml
from equidiff_core.perception.sync import PublishPacer
from equidiff_core.wire import rosmsg
from equidiff_core.wire.pointcloud import cloud_to_msg
from equidiff_core.wire.topics import TOPIC_DIAGNOSTICS, TOPIC_TF_STATIC, camera_color_topic
from equidiff_ros.common import LATCHED_QOS, RELIABLE_QOS, cloud_qos, declare_lab_config, now_ns, wait_for_clock
from equidiff_ros.parameters import LAB_CONFIG, NodeParameter, NodeParameters, parameters_help
from equidiff_ros.runner import run_node

NODE_NAME = "camera_node"

PARAMETERS = NodeParameters(
    LAB_CONFIG,
    NodeParameter("camera", "", "The camera of lab.yaml to publish; empty: every configured camera"),
    NodeParameter("backend", "realsense", "Where the frames come from", choices=tuple(BACKENDS)),
    NodeParameter("bag", "", "replay: the rosbag2 directory holding /cameras/<name>/points"),
    NodeParameter("loop", True, "replay: start over at the end of the bag"),
    NodeParameter("rate", 1.0, "replay: speed factor", Bounds("", gt=0, le=100.0)),
    NodeParameter("restamp", True, "replay: stamp frames with this node's clock (false: the recorded stamps)"),
    NodeParameter(
        "backend_options", "", 'A YAML mapping handed to the backend, e.g. "{width: 424, height: 240}" (twin)'
    ),
    NodeParameter(
        "reliable_clouds",
        False,
        "Publish clouds and images reliably instead of with sensor-data QoS: the lockstep twin sets it, "
        "with voxel_node's, so that no frame it owes a chunk is lost in transport",
    ),
    NodeParameter(
        "publish_color", True, "Publish each frame's colour image as JPEG beside its cloud (replay has none)"
    ),
    NodeParameter("jpeg_quality", DEFAULT_JPEG_QUALITY, "JPEG quality of the colour images", Bounds("", ge=1, le=100)),
)

USAGE = (
    __doc__
    + parameters_help(PARAMETERS)
    + """
usage: camera_node [--ros-args -p backend:=realsense|replay|twin -p camera:=cam_left
                    -p lab_config:=config/lab.yaml -p bag:=bags/episode_0001 -p loop:=true]
"""
)


class CameraNode(Node):
    def __init__(self, node_name: str = NODE_NAME):
        super().__init__(node_name)
        wait_for_clock(self)  # simulated time (the twin): nothing is timed before /clock
        self.lab = declare_lab_config(self)
        param = lambda name: PARAMETERS.declare(self, name)
        name = param("camera")
        self.backend = param("backend")
        bag = param("bag")
        loop = param("loop")
        rate = param("rate")
        restamp = param("restamp")
        options_text = param("backend_options")
        reliable = param("reliable_clouds")
        self.publish_color = param("publish_color")
        self.jpeg_quality = param("jpeg_quality")
        self.configs = [self.lab.camera(name)] if name else list(self.lab.cameras)
        self.factory = rosmsg.RclpyFactory()
        options = parse_yaml(options_text, "backend_options") if options_text else {}
        if not isinstance(options, dict):
            raise ConfigError(f"backend_options must be a YAML mapping, got {options_text!r}")
        clock = lambda: now_ns(self)
        if self.backend == "replay":
            options = {"bag": bag, "loop": loop, "rate": rate, "restamp": restamp, "clock": clock, **options}
        elif self.backend == "realsense":
            options = {"clock": clock, **options}  # pace_hz: set per camera below
        elif self.backend == "twin":
            # the twin renders when read: this node decides when (on the shared clock grid),
            # unless the user asked for the camera's own pacing
            options = {"paced": False, **options}
        # a lockstep twin camera is clocked by the sim itself (simulated time): no wall-clock pacing
        self.clocked_by_source = self.backend == "twin" and bool(options.get("lockstep", False))
        self.on_demand = self.backend == "twin" and not options.get("paced", False) and not self.clocked_by_source
        # build and connect every camera first: a missing device fails the node at once
        self.cameras = []
        try:
            for cfg in self.configs:
                extra = {"pace_hz": cfg.publish_hz} if self.backend == "realsense" else {}
                if self.clocked_by_source:
                    extra = {"slot": [c.name for c in self.lab.cameras].index(cfg.name)}
                camera = make_camera(self.backend, cfg, **{**extra, **options})
                camera.connect()
                self.cameras.append(camera)
        except CameraError:
            self._disconnect_all()
            raise
        self.pubs = {c.name: self.create_publisher(PointCloud2, c.topic, cloud_qos(reliable)) for c in self.configs}
        self.color_pubs = {}
        if self.publish_color:
            self.color_pubs = {
                c.name: self.create_publisher(CompressedImage, camera_color_topic(c.name), cloud_qos(reliable))
                for c in self.configs
            }
        self.stats = {
            c.name: {"published": 0, "read_errors": 0, "last_stamp_ns": None, "color_published": 0, "jpeg_s": 0.0}
            for c in self.configs
        }
        self._publish_tf_static()
        self.diag_pub = self.create_publisher(DiagnosticArray, TOPIC_DIAGNOSTICS, RELIABLE_QOS)
        self.create_timer(1.0, self._publish_diagnostics)
        self._stop = threading.Event()
        self.threads = [
            threading.Thread(target=self._run, args=(cfg, cam), name=f"camera-{cfg.name}", daemon=True)
            for cfg, cam in zip(self.configs, self.cameras)
        ]
        for t in self.threads:
            t.start()
        published = [c.topic for c in self.configs] + [
            camera_color_topic(c.name) for c in self.configs if self.color_pubs
        ]
        self.get_logger().info(f"{self.backend} backend: publishing {published}")

    def _publish_tf_static(self):
        try:
            from tf2_msgs.msg import TFMessage
        except ImportError:
            self.get_logger().info(
                "tf2_msgs is not installed: /tf_static is not published "
                "(the recorder writes the camera extrinsics into bags)"
            )
            return
        self.tf_pub = self.create_publisher(TFMessage, TOPIC_TF_STATIC, LATCHED_QOS)
        self.tf_pub.publish(extrinsics_tf_message(self.configs, self.lab.base_frame, now_ns(self), self.factory))

    def _run(self, cfg, camera):
        log = self.get_logger().get_child(cfg.name)  # a logger per camera: its own warning throttle
        pacer = PublishPacer(cfg.publish_hz)
        pub, stats = self.pubs[cfg.name], self.stats[cfg.name]
        while not self._stop.is_set():
            if self.on_demand and self._stop.wait(pacer.wait_s(time.time())):
                return
            try:
                frame = camera.read(timeout_s=1.0)
            except ReplayFinished as err:
                log.info(str(err))
                return
            except NoFrameYet:
                continue  # the twin's clock is paused (it waits for the policy): nothing is wrong
            except CameraError as err:
                stats["read_errors"] += 1
                log.warning(f"{cfg.name}: {err}", throttle_duration_sec=2.0)
                self._stop.wait(0.05)
                continue
            if not self.clocked_by_source and not pacer.due(time.time()):
                continue  # the device runs faster than publish_hz: skip this frame
            frame = limit_depth(frame, cfg.min_depth, cfg.max_depth)
            if len(frame.points) == 0:
                log.warning(
                    f"{cfg.name}: no points within [{cfg.min_depth}, {cfg.max_depth}] m", throttle_duration_sec=2.0
                )
                continue
            msg = cloud_to_msg(frame.points, frame.colors, frame.stamp_ns, cfg.frame_id, self.factory)
            image_msg = self._color_msg(cfg, frame, log)
            if self._stop.is_set() or not self.context.ok():
                return  # Ctrl-C/SIGTERM shut the context down while this frame was read
            try:
                pub.publish(msg)
                if image_msg is not None:
                    self.color_pubs[cfg.name].publish(image_msg)
            except Exception as err:  # rclpy raises RCLError once the context is gone
                if self.context.ok():
                    raise
                log.debug(f"{cfg.name}: not published, shutting down ({err})")
                return
            stats["published"] += 1
            stats["color_published"] += image_msg is not None
            stats["last_stamp_ns"] = frame.stamp_ns

    def _color_msg(self, cfg, frame, log):
        """The frame's colour image as a JPEG CompressedImage (None when off or the backend has no image)."""
        if not self.color_pubs or frame.image is None:
            return None
        t0 = time.thread_time()  # this thread's CPU: what the encoding costs the machine, not the wait
        try:
            msg = color_image_msg(frame.image, frame.stamp_ns, cfg.frame_id, self.factory, self.jpeg_quality)
        except ImageError as err:
            log.warning(f"{cfg.name}: colour image not published: {err}", throttle_duration_sec=2.0)
            return None
        self.stats[cfg.name]["jpeg_s"] += time.thread_time() - t0
        return msg

    def _publish_diagnostics(self):
        now = now_ns(self)
        for cfg, camera in zip(self.configs, self.cameras):
            s, health = self.stats[cfg.name], camera.health()
            age_ms = None if s["last_stamp_ns"] is None else (now - s["last_stamp_ns"]) / 1e6
            ok = age_ms is not None and age_ms < 3000.0 / cfg.publish_hz
            if health.recovering:
                message = f"recovering: {health.last_recovery_reason}"
            else:
                message = "publishing" if ok else "no recent frames"
            self.diag_pub.publish(
                rosmsg.diagnostic_array(
                    self.factory,
                    now,
                    f"{NODE_NAME}/{cfg.name}",
                    cfg.serial,
                    rosmsg.OK if ok and not health.recovering else rosmsg.WARN,
                    message,
                    {
                        "backend": self.backend,
                        "published": s["published"],
                        "read_errors": s["read_errors"],
                        "age_ms": "none" if age_ms is None else round(age_ms, 1),
                        "resets": health.resets,
                        "reconnects": health.reconnects,
                        "last_recovery_reason": health.last_recovery_reason or "none",
                        "color_published": s["color_published"],
                        "jpeg_cpu_ms": round(1e3 * s["jpeg_s"] / s["color_published"], 2)
                        if s["color_published"]
                        else "none",
                    },
                )
            )

    def _disconnect_all(self):
        for camera in getattr(self, "cameras", []):
            camera.disconnect()

    def shutdown(self):
        if hasattr(self, "_stop"):
            self._stop.set()
            for t in self.threads:
                t.join(timeout=2.0)
        self._disconnect_all()


# the errors that end a start-up with a one-line message (exit 1), not a traceback
STARTUP_ERRORS = (CameraError, ConfigError)


def main(args=None) -> int:
    return run_node(NODE_NAME, USAGE, CameraNode, STARTUP_ERRORS, args)


if __name__ == "__main__":
    sys.exit(main())
