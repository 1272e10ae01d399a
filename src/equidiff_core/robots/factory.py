"""Building a robot backend by name (franka_node's ``backend`` parameter)."""

from __future__ import annotations

from .base import Robot
from .dryrun import DryRunConfig, DryRunRobot
from .franky import FrankyRobot

BACKENDS = ("franky", "dryrun")


def make_robot(backend: str, **kwargs) -> Robot:
    """``make_robot("franky", ip=..., config=FrankyConfig, realtime=...)`` or ``make_robot("dryrun")``.

    Neither needs franky to be built: ``FrankyRobot`` imports it on connect."""
    if backend == "franky":
        return FrankyRobot(**kwargs)
    if backend == "dryrun":
        config = kwargs.pop("config", None)
        return DryRunRobot(config if isinstance(config, DryRunConfig) else DryRunConfig(), **kwargs)
    raise ValueError(f"unknown robot backend {backend!r}; choose one of {BACKENDS}")
