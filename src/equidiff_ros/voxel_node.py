"""voxel_node: the fused 4x64³ voxel grid from the configured cameras' clouds, at the observation rate.

Wiring:
  /cameras/<name>/points (PointCloud2, sensor-data QoS), one subscription per camera
      -> ``wire.pointcloud.msg_to_cloud`` (malformed, in another frame, stamped more than
         ``max_future_stamp_s`` ahead, or unusable by the voxeliser: dropped, counted per camera
         and reason on /diagnostics, with a throttled warning)
      -> ``perception.fusion.CloudFusion`` (one queue per camera; the same rule ``equidiff dataset
         revoxelize`` applies to recorded clouds)
  each cloud, no camera stale: a new complete set within ``slop_s`` (at most ``observation_hz``)?
      -> ``perception.voxels.Voxelizer`` (extrinsics from lab.yaml) -> ``wire.pointcloud.grid_to_voxel_msg``
      -> /voxels (stamp = newest capture stamp of the set)
  timer at ``observation_hz`` -> stale camera? say which (the stale camera has no set to add)
  timer at 1 Hz -> /diagnostics (``voxel_node``: voxelize_ms, per-camera age_ms, drops by reason)

A set is fused the moment its last cloud arrives, not on a timer of our own: a timer's phase
added up to a period of latency, and on the twin's simulated time (which pauses until the
policy has answered this very observation) a grid waiting for a timer tick never came.

Parameters: ``PARAMETERS`` below (``--help``, ``ros2 param describe``, docs/parameters.md).
"""

from __future__ import annotations

import collections
import dataclasses
import re
import sys
import time

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node
from sensor_msgs.msg import PointCloud2

from equidiff_core.config import Bounds, ConfigError, LabConfig
from equidiff_core.perception.fusion import CloudFusion
from equidiff_core.perception.observation import MAX_FUTURE_STAMP_S
from equidiff_core.perception.voxels import VoxelError, VoxelizerConfig
from equidiff_core.wire import rosmsg
from equidiff_core.wire.pointcloud import CloudError, grid_to_voxel_msg, msg_to_cloud
from equidiff_core.wire.topics import TOPIC_DIAGNOSTICS, TOPIC_VOXELS
from equidiff_ros.common import RELIABLE_QOS, VOXEL_QOS, cloud_qos, declare_lab_config, now_ns, wait_for_clock
from equidiff_ros.parameters import LAB_CONFIG, NodeParameter, NodeParameters, bounds_of, parameters_help
from equidiff_ros.runner import run_node

NODE_NAME = "voxel_node"

PARAMETERS = NodeParameters(
    LAB_CONFIG,
    NodeParameter(
        "observation_hz",
        5.0,
        "Most grids per second",
        bounds_of(LabConfig, "observation_hz"),
        default_from="lab.yaml observation_hz",
        number=True,
    ),
    NodeParameter(
        "slop_s", 0.1, "Largest capture-stamp spread of the clouds fused into one grid", Bounds("s", gt=0, le=1.0)
    ),
    NodeParameter(
        "stale_after_s",
        0.5,
        "A camera whose newest cloud is older than this stops the output",
        Bounds("s", gt=0, le=10.0),
    ),
    NodeParameter("queue_size", 5, "Clouds kept per camera for matching", Bounds("", ge=1, le=100)),
    NodeParameter("check_frame_id", True, "Drop clouds whose frame is not the camera's optical frame"),
    NodeParameter("allow_nan_points", False, "Drop NaN/inf points instead of the whole cloud"),
    NodeParameter(
        "max_future_stamp_s",
        MAX_FUTURE_STAMP_S,
        "A cloud stamped further ahead of this node's clock is dropped",
        Bounds("s", ge=0, le=1.0),
        number=True,
    ),
    NodeParameter(
        "reliable_clouds",
        False,
        "Subscribe to the clouds reliably: only with camera_nodes that publish reliably, as the lockstep twin's do",
    ),
    NodeParameter("remove_table", False, "Drop the points below table_z"),
    NodeParameter("table_z", 0.0, "Height below which remove_table drops points, base frame", Bounds("m")),
    NodeParameter(
        "outlier_neighbors",
        0,
        "Statistical outlier removal: neighbours per point (0: off)",
        Bounds("", ge=0, le=100),
    ),
    NodeParameter(
        "outlier_std_ratio",
        2.0,
        "Statistical outlier removal: a point farther than the mean + this many standard deviations goes",
        Bounds("", gt=0, le=100.0),
    ),
)

USAGE = (
    __doc__
    + parameters_help(PARAMETERS)
    + """
usage: voxel_node [--ros-args -p lab_config:=config/lab.yaml -p slop_s:=0.1 -p stale_after_s:=0.5]
"""
)


class VoxelNode(Node):
    def __init__(self, node_name: str = NODE_NAME):
        super().__init__(node_name)
        wait_for_clock(self)  # simulated time (the twin): nothing is timed before /clock
        self.lab = declare_lab_config(self)
        param = lambda name: PARAMETERS.declare(self, name)
        hz = PARAMETERS.declare(self, "observation_hz", self.lab.observation_hz)
        self.slop_ns = int(param("slop_s") * 1e9)
        self.stale_ns = int(param("stale_after_s") * 1e9)
        queue_size = param("queue_size")
        self.check_frame_id = param("check_frame_id")
        self.allow_nan = param("allow_nan_points")
        self.max_future_ns = int(param("max_future_stamp_s") * 1e9)
        reliable = param("reliable_clouds")
        remove_table = param("remove_table")
        table_z = param("table_z")
        cleanup = VoxelizerConfig(
            table_z=table_z if remove_table else None,
            outlier_neighbors=param("outlier_neighbors"),
            outlier_std_ratio=param("outlier_std_ratio"),
        )
        self.cameras = list(self.lab.cameras)
        self.names = [c.name for c in self.cameras]
        self.fusion = CloudFusion(dataclasses.replace(self.lab, observation_hz=hz), self.slop_ns, queue_size, cleanup)
        self.matcher = self.fusion.matcher  # the camera queues: their ages say which camera is stale
        self.factory = rosmsg.RclpyFactory()
        for cam in self.cameras:
            self.create_subscription(
                PointCloud2, cam.topic, lambda msg, cam=cam: self._on_cloud(cam, msg), cloud_qos(reliable)
            )
        self.pub = self.create_publisher(PointCloud2, TOPIC_VOXELS, VOXEL_QOS)
        self.diag_pub = self.create_publisher(DiagnosticArray, TOPIC_DIAGNOSTICS, RELIABLE_QOS)
        self.dropped = {n: 0 for n in self.names}
        self.dropped_by_reason: collections.Counter[str] = collections.Counter()
        self.last_drop = ""
        self._last_warned: dict[tuple[str, ...], float] = {}
        self.published = 0
        self.skipped_stale = 0
        self.voxelize_ms = float("nan")
        self.state = "waiting for clouds"
        self.create_timer(1.0 / hz, self._on_tick)
        self.create_timer(1.0, self._publish_diagnostics)
        self.get_logger().info(f"fusing {[c.topic for c in self.cameras]} into {TOPIC_VOXELS} at {hz} Hz")

    def _on_cloud(self, cam, msg):
        try:
            cloud = msg_to_cloud(
                msg, drop_invalid=self.allow_nan, frame_id=cam.frame_id if self.check_frame_id else None
            )
            rosmsg.check_not_future(cloud.stamp_ns, now_ns(self), self.max_future_ns, "a cloud")
            self.fusion.add(cam.name, cloud.stamp_ns, cloud)
            self._publish_new_set()
        except (CloudError, rosmsg.MessageError, VoxelError) as err:
            # VoxelError: a cloud the decoder let through but the voxeliser cannot use; either way
            # this one message is dropped and the node goes on
            reason = str(getattr(err, "reason", "voxelizer"))
            self.dropped[cam.name] += 1
            self.dropped_by_reason[reason] += 1
            self.last_drop = f"{cam.name}: {reason}: {err}"
            # throttled per camera and kind of problem (numbers removed), so each is seen
            self._warn((cam.name, re.sub(r"\d+", "#", str(err))), f"dropped a cloud on {cam.topic} ({reason}): {err}")

    def _stale_cameras(self) -> bool:
        """Say which cameras are stale (and count it); True when any is."""
        now = now_ns(self)
        stale = self.matcher.stale(now, self.stale_ns)
        if stale:
            self.skipped_stale += 1
            ages = self.matcher.ages_ns(now)
            why = ", ".join(
                f"{n} (never received)" if ages[n] is None else f"{n} (last cloud {ages[n] / 1e9:.2f} s ago)"
                for n in stale
            )
            self.state = f"stale: {why}"
            # keyed by which cameras are stale: a new set is said at once, not hidden behind the last
            self._warn(("stale", *stale), f"not publishing {TOPIC_VOXELS}: stale camera(s) {why}")
        return bool(stale)

    def _warn(self, key: tuple[str, ...], message: str) -> None:
        """A warning at most every 2 s per ``key`` (a kind of problem), so one kind never hides another."""
        t = time.monotonic()
        if t - self._last_warned.get(key, -1e9) >= 2.0:
            self._last_warned[key] = t
            self.get_logger().warning(message)

    def _on_tick(self):
        if not self._stale_cameras() and self.matcher.peek() is None:
            self.state = f"no cloud set within slop {self.slop_ns / 1e9:.3f} s"
            self.get_logger().warning(
                f"not publishing {TOPIC_VOXELS}: the cameras' newest clouds are not "
                f"within slop_s {self.slop_ns / 1e9:.3f} s of each other",
                throttle_duration_sec=2.0,
            )

    def _publish_new_set(self):
        if self._stale_cameras():
            return  # a camera is stale: no grid until it is back
        t0 = time.perf_counter()
        out = self.fusion.next_grid()
        if out is None:
            return  # no new complete set yet, or not due (cameras faster than observation_hz)
        self.voxelize_ms = (time.perf_counter() - t0) * 1e3
        stamp_ns, grid = out
        ws = self.lab.workspace
        self.pub.publish(grid_to_voxel_msg(grid, ws.lower, ws.voxel_size, stamp_ns, self.lab.base_frame, self.factory))
        self.published += 1
        self.state = "publishing"

    def _publish_diagnostics(self):
        now = now_ns(self)
        ages = self.matcher.ages_ns(now)
        stats = self.fusion.voxelizer.last_stats
        values = {
            "voxelize_ms": self.voxelize_ms,
            "published": self.published,
            "skipped_stale": self.skipped_stale,
            "points_used": stats.points_used if stats else 0,
            "occupied_voxels": stats.occupied if stats else 0,
        }
        for n in self.names:
            values[f"{n}_age_ms"] = "none" if ages[n] is None else round(ages[n] / 1e6, 1)
            values[f"{n}_dropped"] = self.dropped[n]
        values.update({f"dropped_{reason}": count for reason, count in sorted(self.dropped_by_reason.items())})
        values["last_drop"] = self.last_drop
        level = rosmsg.OK if self.state == "publishing" else rosmsg.WARN
        self.diag_pub.publish(rosmsg.diagnostic_array(self.factory, now, NODE_NAME, "", level, self.state, values))

    def shutdown(self):
        pass


# the errors that end a start-up with a one-line message (exit 1), not a traceback
STARTUP_ERRORS = (ConfigError, VoxelError, ValueError)


def main(args=None) -> int:
    return run_node(NODE_NAME, USAGE, VoxelNode, STARTUP_ERRORS, args)


if __name__ == "__main__":
    sys.exit(main())
