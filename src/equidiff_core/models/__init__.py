"""Networks of the policies.

* ``unet1d``: Diffusion Policy's ConditionalUnet1D (plain torch), shared by both policies.
* ``equivariant``: the escnn EquiDiff noise predictor (C_N voxel encoder, gripper-state and
  action embeddings, U-Net shared over group elements, equivariant decoder) and its export.
* ``plain``: the same noise predictor as plain torch modules (inference without escnn).
* ``baseline``: DiffPo-C (Vo), a non-equivariant 3D conv encoder with the same U-Net.
* ``action_space``: the irreps the denoised vectors carry.
* ``state``: a network's learned state for checkpoints, independent of escnn's train/eval caches.

Importing this package imports no escnn; ``models.equivariant`` does.
"""
