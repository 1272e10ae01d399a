"""Executing pose chunks safely: safety checks and filter, time-indexed chunk scheduling, the control loop.

Pure and ROS-free; the franka node only wires ROS topics to ``Controller``.
"""

from .config import (
    ControlConfig,
    FrankyConfig,
    SafetyConfig,
    SchedulerConfig,
    check_home_inside,
    load_control_config,
)
from .controller import Command, Controller, ControllerStats, ControllerStatus
from .safety import (
    FilteredTarget,
    SafetyFilter,
    SafetyRejection,
    check_chunk,
)
from .scheduler import ChunkScheduler, Setpoint
from .stops import AcknowledgeRefused

__all__ = [
    "AcknowledgeRefused",
    "ChunkScheduler",
    "Command",
    "ControlConfig",
    "Controller",
    "ControllerStats",
    "ControllerStatus",
    "FilteredTarget",
    "FrankyConfig",
    "SafetyConfig",
    "SafetyFilter",
    "SafetyRejection",
    "SchedulerConfig",
    "Setpoint",
    "check_chunk",
    "check_home_inside",
    "load_control_config",
]
