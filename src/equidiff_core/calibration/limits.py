"""The limits a calibration's poses must keep: franka_node's own, from lab.yaml and control.yaml.

Calibration moves the arm with the same control loop as franka_node (``control.Controller``:
safety box, orientation cone, speed limits, divergence and joint-limit stops; see
``capture.ControlledArm``). That loop clips a target outside the box to its wall and swings a
tilted one back into the cone: right for a policy's stream, wrong for a calibration pose, whose
image would then be taken somewhere else. So a plan is checked here first, and a pose the loop
would alter is an error before anything moves.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from .. import geometry
from ..config import LabConfig, SafetyBox, default_config_dir
from ..control.config import ControlConfig, load_control_config
from ..control.safety import SafetyFilter
from .board import CalibrationError


@dataclass(frozen=True)
class MotionLimits:
    """The safety box (lab.yaml ``safety_box``) and franka_node's control settings (control.yaml)."""

    box: SafetyBox
    control: ControlConfig

    @classmethod
    def load(cls, lab: LabConfig, control_path: str | Path | None = None) -> MotionLimits:
        return cls(lab.safety_box, load_control_config(control_path or default_config_dir() / "control.yaml"))

    @property
    def _filter(self) -> SafetyFilter:
        return SafetyFilter(self.box, self.control.safety)

    @property
    def lower(self) -> np.ndarray:
        """The lowest corner franka_node lets a target reach: the box shrunk by box_margin_m."""
        return self._filter.lower

    @property
    def upper(self) -> np.ndarray:
        return self._filter.upper

    @property
    def max_tilt_rad(self) -> float:
        return self.control.safety.max_tilt_rad

    def clamp(self, T: np.ndarray) -> np.ndarray:
        """``T`` moved into the box and tilted back into the cone, as the control loop's filter
        would (for a target that is not a plan: the SpaceMouse's, at a capture)."""
        R = geometry.limit_tilt(np.asarray(T[:3, :3], dtype=np.float64), self.max_tilt_rad)
        return geometry.make_pose(R, self._filter.clip_position(T[:3, 3]))

    def check(self, poses: list[np.ndarray], start: np.ndarray | None = None) -> None:
        """Raise CalibrationError naming every pose (and every move between them, from ``start``
        when given) that leaves the safety box or the orientation cone."""
        lower, upper = self.lower, self.upper
        cone = math.degrees(self.max_tilt_rad)
        problems = []
        for k, T in enumerate(poses):
            try:
                geometry.validate_pose(np.asarray(T, dtype=np.float64), tol=self.control.safety.orthonormal_tol)
            except geometry.GeometryError as err:
                problems.append(f"pose {k + 1} is not a valid pose: {err}")
                continue
            p = T[:3, 3]
            if np.any(p < lower) or np.any(p > upper):
                problems.append(
                    f"pose {k + 1} puts the TCP at {np.round(p, 3).tolist()} m, outside where targets may go "
                    f"{np.round(lower, 3).tolist()} .. {np.round(upper, 3).tolist()} m"
                )
            tilt = math.degrees(geometry.tilt_angle(T[:3, :3]))
            if tilt > cone + 1e-6:
                problems.append(f"pose {k + 1} tilts the tool {tilt:.1f} deg from straight down (cone {cone:.0f} deg)")
        if not problems:
            # The box is convex, so straight moves between poses inside it stay inside; a turn
            # between two orientations inside the cone can still swing out of it midway.
            path = ([start] if start is not None else []) + list(poses)
            for k, (a, b) in enumerate(itertools.pairwise(path)):
                turn = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([a[:3, :3], b[:3, :3]])))
                worst = max(geometry.tilt_angle(R) for R in turn(np.linspace(0.0, 1.0, 21)).as_matrix())
                if math.degrees(worst) > cone + 1e-6:
                    what = "the start" if start is not None and k == 0 else f"pose {k + (start is None)}"
                    problems.append(
                        f"the turn from {what} to pose {k + 1 + (start is None)} swings the tool "
                        f"{math.degrees(worst):.1f} deg from straight down (cone {cone:.0f} deg)"
                    )
        if problems:
            raise CalibrationError(
                f"{len(problems)} problem(s) with the calibration poses; nothing was moved:\n  "
                + "\n  ".join(problems)
                + "\n(targets stay inside lab.yaml's safety_box, its floor raised by floor_margin_m, less control.yaml's "
                "safety.box_margin_m; the cone is "
                "control.yaml's safety.max_tilt_rad; franka_node's control loop would clip these poses, so the "
                "images would not show them)"
            )
