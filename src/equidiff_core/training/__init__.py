"""Training the policies: ``equidiff train`` from bags to a run directory.

* ``config``: what a run is asked for (``TrainConfig``), what it gives back, ``auto`` resolved on this machine
* ``batches``: training batches, resident on the model's device or from a loader, one sample order
* ``distributed``: data-parallel training across processes (torchrun)
* ``loop``: the training loop shared by EquiDiff and the baseline (``train``)
* ``callbacks``: the held-out action error, a progress bar and the plot
* ``job``: one ``equidiff train`` run (``run_training``)
* ``distill``: a finished run's few-step student (``equidiff distill``, ``run_distillation``)
* ``process``: ``python -m equidiff_core.training.process SPEC_JSON``, one run in a process of its own
"""
