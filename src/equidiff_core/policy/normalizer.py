"""Action / gripper-state normaliser, the official EquiDiff scheme.

* x and y: centred on the workspace centre and divided by ONE shared half-range, so a rotation
  about the centre stays a rotation of the normalised (x, y) (the network's rho1 acts on it).
  The half-range is the largest horizontal distance from the centre in the data, the
  rotation-closed version of "max |x|, |y|": rotation augmentation never leaves [-1, 1].
* z: min-max to [-1, 1].
* rot6d and gripper width: unchanged (already O(1)).
* relative control's translation deltas: one shared scale, the workspace edge (a delta between
  two poses inside the workspace is then within [-1, 1] per component).

It is fitted on absolute actions and gripper states together (they live in the same space) and
saved in checkpoints as plain numbers.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..config import Workspace

MIN_RANGE = 1e-3  # m; a degenerate axis (all z equal) falls back to +- this


class NormalizerError(ValueError):
    pass


@dataclass(frozen=True)
class Normalizer:
    center_xy: tuple[float, float]
    xy_scale: float
    z_min: float
    z_max: float
    rel_translation_scale: float

    @classmethod
    def fit(cls, actions: np.ndarray, ee: np.ndarray, workspace: Workspace) -> Normalizer:
        actions = np.asarray(actions, dtype=np.float64).reshape(-1, 10)
        ee = np.asarray(ee, dtype=np.float64).reshape(-1, 10)
        data = np.concatenate([actions, ee], 0)
        if len(data) == 0:
            raise NormalizerError("cannot fit a normaliser on no data")
        if not np.isfinite(data).all():
            raise NormalizerError("actions or gripper states contain NaN or inf")
        c = np.asarray(workspace.center[:2], dtype=np.float64)
        radius = float(np.linalg.norm(data[:, :2] - c, axis=1).max())
        z_lo, z_hi = float(data[:, 2].min()), float(data[:, 2].max())
        if z_hi - z_lo < 2 * MIN_RANGE:
            mid = (z_hi + z_lo) / 2
            z_lo, z_hi = mid - MIN_RANGE, mid + MIN_RANGE
        return cls((float(c[0]), float(c[1])), max(radius, MIN_RANGE), z_lo, z_hi, float(workspace.edge))

    @classmethod
    def from_workspace(cls, workspace: Workspace) -> Normalizer:
        """Data-free default: the workspace cube's own extent."""
        half = workspace.edge / 2
        c = workspace.center
        return cls((c[0], c[1]), half * np.sqrt(2), c[2] - half, c[2] + half, float(workspace.edge))

    def to_dict(self) -> dict:
        # plain floats: numpy scalars here made a checkpoint unloadable with torch.load(weights_only=True)
        return {
            "center_xy": [float(v) for v in self.center_xy],
            "xy_scale": float(self.xy_scale),
            "z_min": float(self.z_min),
            "z_max": float(self.z_max),
            "rel_translation_scale": float(self.rel_translation_scale),
        }

    @classmethod
    def from_dict(cls, d: dict) -> Normalizer:
        try:
            return cls(
                tuple(float(v) for v in d["center_xy"]),
                float(d["xy_scale"]),
                float(d["z_min"]),
                float(d["z_max"]),
                float(d["rel_translation_scale"]),
            )
        except (KeyError, TypeError, ValueError) as err:
            raise NormalizerError(f"malformed normaliser {d!r}: {err}") from err

    # --- absolute 10-D vectors (actions and gripper states); numpy or torch, any leading dims

    def _affine(self, x):
        scale = [self.xy_scale, self.xy_scale, (self.z_max - self.z_min) / 2] + [1.0] * 7
        offset = [self.center_xy[0], self.center_xy[1], (self.z_max + self.z_min) / 2] + [0.0] * 7
        if isinstance(x, torch.Tensor):
            return (
                torch.tensor(scale, dtype=x.dtype, device=x.device),
                torch.tensor(offset, dtype=x.dtype, device=x.device),
            )
        return np.asarray(scale, dtype=x.dtype), np.asarray(offset, dtype=x.dtype)

    def normalize(self, x):
        scale, offset = self._affine(x)
        return (x - offset) / scale

    def unnormalize(self, x):
        scale, offset = self._affine(x)
        return x * scale + offset
