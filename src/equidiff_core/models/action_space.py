"""The vectors the noise predictor denoises, and how C_N acts on them (no escnn, no torch needed).

The network sees each action step as a vector whose entries are grouped into SO(2) irreps:
a frequency-1 entry pair rotates as rho1(theta), frequency 2 as rho1(2 theta), frequency 0 is
invariant. ``freqs`` lists the blocks in order; escnn builds the matching field type from it.

* absolute control (10 entries): [x, y | r00, r10 | r01, r11 | r02, r12 | z | width] in the
  normaliser's frame (x, y about the workspace centre), i.e. the paper's rho1^4 + rho0^2.
* relative control (13 entries): the world-frame delta A = T_target T_now^-1 (positions about
  the workspace centre) as [t_x, t_y | t_z | P vec_r(dR) | width] with the paper's change of
  basis P (geometry.P_REL_ROT): rho1 + rho0 + (rho0^3 + rho1^2 + rho2) + rho0.
"""

from __future__ import annotations

import numpy as np

from .. import geometry

# Absolute: model index i takes action entry ABS_ORDER[i].
ABS_ORDER = (0, 1, 3, 6, 4, 7, 5, 8, 2, 9)
ABS_FREQS = (1, 1, 1, 1, 0, 0)
ABS_INVERSE = tuple(int(i) for i in np.argsort(ABS_ORDER))
REL_FREQS = (1, 0, *geometry.REL_ROT_IRREPS, 0)  # t_xy, t_z, rotation blocks, width
REL_DIM = 13
EE_FREQS = ABS_FREQS  # the gripper state always enters as an absolute pose


def dim_of(freqs: tuple[int, ...]) -> int:
    return sum(1 if k == 0 else 2 for k in freqs)


def freqs_for(control: str) -> tuple[int, ...]:
    return ABS_FREQS if control == "absolute" else REL_FREQS


def rep_matrix(freqs: tuple[int, ...], theta: float) -> np.ndarray:
    """Block-diagonal matrix of g (rotation by theta) acting on a model-space vector."""
    return geometry.irrep_block_diag(theta, tuple(freqs))
