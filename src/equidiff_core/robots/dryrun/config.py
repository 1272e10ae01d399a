"""Settings of the dry-run robot: where it pretends to start and how much of what it is sent it keeps."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class DryRunConfig:
    """The pretended arm's starting TCP pose, width and joints; how often commands are logged and how many are kept."""

    initial_position: tuple[float, float, float] = (0.45, 0.0, 0.30)
    initial_quaternion_xyzw: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)
    initial_width: float = 0.08
    # the FR3's ready pose, well inside its joint limits (zeros would sit outside joints 4 and 6's)
    joint_positions: tuple[float, ...] = (0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785)
    log_period_s: float = 1.0
    keep_last: int = 10000
