"""Bench logic shared by the ``equidiff bench`` / ``equidiff check`` commands (each command is argument
parsing plus one call into here: typed settings in, the bench's JSON line out as a dict, ``BenchError`` when
it cannot run; progress through the module's logger).

* ``conditioning``: does a policy look at its observation? Its features and its actions when the block moves.
* ``equivariance_check``: C4 and 45 deg equivariance errors of every inference path (``check equivariance``).
* ``overfit``: can a policy fit two synthetic demos (``bench overfit``; the suite runs a short version)?
* ``training_runs``: ``equidiff train`` runs side by side, their recipes and the training-fit gate.
* ``generalization``: EquiDiff against two baselines on unseen object yaw (train, gate, roll out).
* ``chunk_modes``: whole chunks, replace, execution horizon and real-time chunking by latency, in the twin.
* ``sample_efficiency``: the sample-efficiency bench (success against the number of demos) and its plot.
* ``voxelize``: fusing three clouds into the grid, timed against open3d, on a ray-cast synthetic scene.
* ``timing``: what ``bench policy`` / ``bench train`` measure, on the CPU or CUDA (inference modes, training
  steps and their CPU variants); ``cost``: parameters and FLOPs per sample;
  ``throughput``: the two benches' runs, those timings assembled into one JSON line each.
* ``images``: what recording the cameras' JPEG images costs (bytes and CPU per frame, the twin's renders).
* ``stats``: every success rate with n and its Wilson 95 % interval; paired comparisons on the same scenes
  (McNemar's exact test, a paired bootstrap interval of the difference); the scenes a comparison needs.
* ``fault_campaign``: the fault campaign of ``bench safety`` against franky-sim through franka_node (its ROS side passed in).
"""

from equidiff_core.runtime.jobs import JobError


class BenchError(JobError):
    """A bench or check could not run: exit status 2 for settings or inputs it cannot run with (out of range,
    missing or mismatched demos, runs trained with different recipes), 1 when its work failed (a training)."""
