"""The policy's input, built one way from raw robot data.

Training (``dataset``), the live ``policy_node`` and the twin's in-process evaluation
(``twin.evaluate``) all build the model's observation here, so the three cannot drift apart
(diffusion_policy's ``real_inference_util`` does the same for its real robot).

An observation is the voxel grid at its stamp t together with the TCP pose and the gripper
width measured nearest to t. Both must lie within ``STATE_TOLERANCE_S`` of t, or there is no
observation at t: training drops the step and the live node skips the cycle, so the robot
holds still rather than act on a guessed state. The gripper width is the sum of the two
finger joints of ``/franka/joint_states``; a joint state without them is no gripper state.
"""

from __future__ import annotations

import collections
from typing import Any

import numpy as np

from .. import geometry

__all__ = ["MAX_FUTURE_STAMP_S", "STATE_TOLERANCE_S", "StateHistory", "ee_input", "nearest"]

# At franka_node's 100 Hz state rate the nearest state is at most 5 ms away; 50 ms leaves room
# for a late message without pairing an observation with a state from another moment of motion.
STATE_TOLERANCE_S = 0.05

# A camera cloud (at voxel_node) or a voxel grid (at policy_node) stamped further ahead of the
# receiving node's clock than this is refused: a capture is never in the future, and a stamp
# from a wrong clock would make every age check pass. Room for clock skew between machines and
# a /clock message in flight on simulated time (the nodes' ``max_future_stamp_s`` parameter).
MAX_FUTURE_STAMP_S = 0.05


def nearest(sorted_ns: np.ndarray, t_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Index of and |distance| to the nearest element of ``sorted_ns`` (ascending) for each ``t_ns``."""
    sorted_ns, t_ns = np.asarray(sorted_ns, dtype=np.int64), np.asarray(t_ns, dtype=np.int64)
    if len(sorted_ns) == 0:
        raise ValueError("no stamps to match against")
    if len(sorted_ns) == 1:
        return np.zeros(len(t_ns), dtype=np.int64), np.abs(sorted_ns[0] - t_ns)
    j = np.clip(np.searchsorted(sorted_ns, t_ns), 1, len(sorted_ns) - 1)
    left, right = sorted_ns[j - 1], sorted_ns[j]
    idx = np.where(np.abs(t_ns - left) <= np.abs(right - t_ns), j - 1, j)  # ties go to the earlier state
    return idx, np.abs(sorted_ns[idx] - t_ns)


def ee_input(tcp_pose: np.ndarray, gripper_width: float) -> np.ndarray:
    """The policy's (10,) float32 robot-state input: TCP position, rot6d, gripper width."""
    return geometry.pose_to_action(
        np.asarray(tcp_pose, dtype=np.float64), np.asarray(gripper_width, dtype=np.float64)
    ).astype(np.float32)


class StateHistory:
    """Recent (stamp, value) samples of one robot-state stream, matched to observation stamps.

    The live node keeps one for TCP poses and one for gripper widths; ``nearest`` applies the
    same rule as training (``nearest`` above, within ``STATE_TOLERANCE_S`` unless told)."""

    def __init__(self, maxlen: int = 200):
        self._samples: collections.deque[tuple[int, Any]] = collections.deque(maxlen=maxlen)

    def add(self, stamp_ns: int, value: Any) -> None:
        self._samples.append((int(stamp_ns), value))

    def nearest(self, t_ns: int, tolerance_ns: int | None = None) -> Any | None:
        """The sample nearest ``t_ns`` if within the tolerance, else None."""
        if not self._samples:
            return None
        tolerance_ns = round(STATE_TOLERANCE_S * 1e9) if tolerance_ns is None else tolerance_ns
        samples = sorted(self._samples, key=lambda s: s[0])  # arrival order need not be stamp order
        (i,), (distance,) = nearest(np.array([s[0] for s in samples]), np.array([t_ns]))
        return samples[i][1] if distance <= tolerance_ns else None

    def __len__(self) -> int:
        return len(self._samples)
