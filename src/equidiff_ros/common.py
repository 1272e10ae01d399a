"""Shared wiring for every node: QoS profiles of the topic contract, the lab config parameter, stamps.

The QoS profiles here are the ones docs/architecture.md lists; nodes never build their own.
"""

from __future__ import annotations

from pathlib import Path

from rclpy.node import Node
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy,
                       qos_profile_sensor_data)

from equidiff_core.config import LabConfig, default_config_dir, load_lab_config

SENSOR_QOS = qos_profile_sensor_data  # best effort, volatile, keep last 5
RELIABLE_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                          durability=DurabilityPolicy.VOLATILE, history=HistoryPolicy.KEEP_LAST)
VOXEL_QOS = QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.VOLATILE, history=HistoryPolicy.KEEP_LAST)
LATCHED_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL, history=HistoryPolicy.KEEP_LAST)

TOPIC_VOXELS = "/voxels"
TOPIC_EE_POSE = "/franka/ee_pose"
TOPIC_JOINT_STATES = "/franka/joint_states"
TOPIC_COMMAND_CHUNK = "/franka/command_chunk"
TOPIC_EXECUTED_TARGET = "/franka/executed_target"
TOPIC_DIAGNOSTICS = "/diagnostics"
TOPIC_JOY = "/spacenav/joy"
TOPIC_RECORDER_COMMAND = "/recorder/command"


def declare_lab_config(node: Node) -> LabConfig:
    """Declare the `lab_config` parameter (path to lab.yaml; default: the installed one) and load it."""
    default = str(default_config_dir() / "lab.yaml")
    path = node.declare_parameter("lab_config", default).value
    return load_lab_config(Path(path))


def now_ns(node: Node) -> int:
    return node.get_clock().now().nanoseconds
