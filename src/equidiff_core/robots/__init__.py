"""Robot backends behind one interface (``base.Robot``): ``franky`` (FR3 or franky-sim) and ``dryrun``.

One package per backend, each with its config dataclass; ``make_robot`` builds one by name.
"""

from .base import (
    ARM_JOINT_NAMES,
    FINGER_JOINT_NAMES,
    STOP_KINDS,
    JointLimits,
    Robot,
    RobotError,
    RobotState,
    RobotStopped,
    UserStopPressed,
)
from .factory import BACKENDS, make_robot

__all__ = [
    "ARM_JOINT_NAMES",
    "BACKENDS",
    "FINGER_JOINT_NAMES",
    "STOP_KINDS",
    "JointLimits",
    "Robot",
    "RobotError",
    "RobotState",
    "RobotStopped",
    "UserStopPressed",
    "make_robot",
]
