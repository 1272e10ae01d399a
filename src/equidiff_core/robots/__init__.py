"""Robot backends behind one interface (``base.Robot``): ``franky`` (FR3 or franky-sim) and ``dryrun``.

Backends are imported lazily so the dry run needs neither franky nor a robot.
"""

from __future__ import annotations

from .base import (
    ARM_JOINT_NAMES,
    FINGER_JOINT_NAMES,
    STOP_KINDS,
    Robot,
    RobotError,
    RobotState,
    RobotStopped,
    UserStopPressed,
)

BACKENDS = ("franky", "dryrun")


def make_robot(backend: str, **kwargs) -> Robot:
    """``make_robot("franky", ip=..., config=FrankyConfig, realtime=...)`` or ``make_robot("dryrun")``."""
    if backend == "franky":
        from .franky import FrankyRobot

        return FrankyRobot(**kwargs)
    if backend == "dryrun":
        from .dryrun import DryRunConfig, DryRunRobot

        config = kwargs.pop("config", None)
        return DryRunRobot(config if isinstance(config, DryRunConfig) else DryRunConfig(), **kwargs)
    raise ValueError(f"unknown robot backend {backend!r}; choose one of {BACKENDS}")


__all__ = [
    "ARM_JOINT_NAMES",
    "BACKENDS",
    "FINGER_JOINT_NAMES",
    "STOP_KINDS",
    "Robot",
    "RobotError",
    "RobotState",
    "RobotStopped",
    "UserStopPressed",
    "make_robot",
]
