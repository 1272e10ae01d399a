"""Dry-run robot backend: logs what would be sent and pretends to track it perfectly (``make_robot("dryrun")``)."""

from .config import DryRunConfig
from .robot import DryRunRobot

__all__ = ["DryRunConfig", "DryRunRobot"]
