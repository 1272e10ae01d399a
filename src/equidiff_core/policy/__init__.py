"""The policy around the networks (``models``): what is built, trained, saved and run at inference.

* ``presets``: typed model presets, saved inside every checkpoint
* ``diffusion``: the two diffusion policies (EquiDiff and the DiffPo-C baseline), ``make_policy``
* ``normalizer``: the action / gripper-state normaliser
* ``augment``: training augmentation and the voxel input builder every path shares
* ``file``: policy files on disk: the exported format, checked loading, atomic saving
* ``inference``: ``load_inference_policy`` and the sampling paths of ``InferencePolicy``
* ``chunk_sizing``: how many steps each chunk carries and how many run before the next answer
"""
