"""Shared wiring for every node: QoS profiles of the topic contract, the lab config parameter, stamps.

The QoS profiles here are the ones docs/architecture.md lists; nodes never build their own.
"""

from __future__ import annotations

from pathlib import Path

from rclpy.node import Node
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
    qos_profile_sensor_data,
)

from equidiff_core.config import (
    LabConfig,
    default_config_dir,
    from_dict,
    load_lab_config,
)
from equidiff_ros.parameters import LAB_CONFIG, config_parameters, declare

SENSOR_QOS = qos_profile_sensor_data  # best effort, volatile, keep last 5
RELIABLE_QOS = QoSProfile(
    depth=10,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
    history=HistoryPolicy.KEEP_LAST,
)
VOXEL_QOS = QoSProfile(
    depth=5,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
    history=HistoryPolicy.KEEP_LAST,
)
# policy_node and viz_node read /voxels best effort. A reliable reader is in its writer's acknowledgement
# set, and Fast DDS held back voxel_node's grids from *every* reader (twin_node, the recorder)
# while one reliable reader did not acknowledge: a SIGSTOPped policy_node did that in the twin,
# and sometimes (when the pause outlived the participant lease) the writer never delivered
# again, so the next episode stalled at "voxel_node: no /voxels". A frozen viewer would do the
# same. A best-effort reader costs the writer nothing; it loses a grid when it falls behind its
# queue, which the lockstep twin never lets the policy do (the next grid exists only once this
# one is answered or skipped) and which a viewer can afford. The recorder stays reliable: a bag
# must not lose grids.
VOXEL_READER_QOS = QoSProfile(
    depth=5,
    reliability=ReliabilityPolicy.BEST_EFFORT,
    durability=DurabilityPolicy.VOLATILE,
    history=HistoryPolicy.KEEP_LAST,
)
# The twin on simulated time owes every camera frame a chunk: a frame whose cloud is lost in
# transport (best effort drops a large sample when a queue overflows) would hold the sim until
# its stall timeout. So there both ends of the cloud topics are reliable (``reliable_clouds``);
# a best-effort subscriber (the recorder, viz) still matches a reliable publisher.
RELIABLE_CLOUD_QOS = QoSProfile(
    depth=5,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
    history=HistoryPolicy.KEEP_LAST,
)
LATCHED_QOS = QoSProfile(
    depth=1,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
    history=HistoryPolicy.KEEP_LAST,
)


def cloud_qos(reliable: bool) -> QoSProfile:
    """QoS of the camera cloud topics: sensor data in the lab, reliable in the lockstep twin."""
    return RELIABLE_CLOUD_QOS if reliable else SENSOR_QOS


def declare_config(node, cls):
    """Declare one ROS parameter per field of config dataclass ``cls`` (default and description from
    the field, ``parameters.config_parameters``) and build the config from their values."""
    parameters = config_parameters(cls)
    values = {p.name: parameters.declare(node, p.name) for p in parameters}
    return from_dict(cls, values, node.get_name())


def declare_lab_config(node: Node) -> LabConfig:
    """Declare the ``lab_config`` parameter (default: the installed lab.yaml) and load the file."""
    path = declare(node, LAB_CONFIG, str(default_config_dir() / "lab.yaml"))
    return load_lab_config(Path(path))


def now_ns(node: Node) -> int:
    return node.get_clock().now().nanoseconds


def uses_sim_time(node: Node) -> bool:
    return bool(node.get_parameter("use_sim_time").value)


def wait_for_clock(node: Node, log_every_s: float = 5.0) -> None:
    """With ``use_sim_time``, wait until ``/clock`` has given the node a time (saying so meanwhile).

    Every node calls this first: on simulated time a node's clock reads 0 until the first
    ``/clock`` message, and stamps, ages and timers would be nonsense until then. In the lab
    (wall time) it returns at once.
    """
    import os
    import time

    import rclpy

    if not uses_sim_time(node):
        return
    start = time.monotonic()
    last = start - log_every_s + 1.0  # say so after 1 s (a running twin answers within ms), then every log_every_s
    while node.context.ok() and node.get_clock().now().nanoseconds == 0:
        if time.monotonic() - last >= log_every_s:
            last = time.monotonic()
            node.get_logger().warning(
                f"use_sim_time is true but no /clock has arrived after {last - start:.0f} s: waiting. Is twin_node "
                f"running on ROS_DOMAIN_ID={os.environ.get('ROS_DOMAIN_ID', '0')}? (In the lab, leave "
                f"use_sim_time false.)"
            )
        rclpy.spin_once(node, timeout_sec=0.1)


def node_clock(node: Node, stall_s: float | None = None):
    """The node's time as an ``equidiff_core.runtime.clock.Clock`` for loops that tick at a rate; on simulated
    time ``stall_s`` bounds how long a sleep waits for a clock that stands still (``PolledClock``)."""
    from equidiff_core.runtime.clock import PolledClock, WallClock

    return PolledClock(lambda: now_ns(node), stall_s=stall_s) if uses_sim_time(node) else WallClock()
