"""The digital twin: franky-sim's FR3 with a tabletop task, simulated cameras, a scripted expert.

* ``config``: ``TwinConfig`` (config/twin.yaml)
* ``scene``: MJCF additions, seeded randomisation (``sample_scene``), success test
* ``sim``: ``TwinSim`` (libfranka server, real-time loop, shared state) and ``DirectSim``
* ``shared_state``: seqlock shared memory carrying the sim state to camera processes
* ``expert``: grasp-lift-place planner
* ``lockstep``: when the sim may step on simulated time (camera frames, policy chunks, stalls)
* ``episode``: one episode's sequence wherever it runs, live or in-process (``run_episode``)
* ``demos`` / ``evaluate``: in-process demonstrations and closed-loop evaluation on the sim clock
* ``run_summary``: what the main job reports; ``processes``: starting and stopping node processes
* ``node_specs``: the twin stack's nodes and their parameters; ``gate``: which policy chunks
  the supervisor (``equidiff_ros.twin``) lets through, and when
* ``calibration``: camera calibration in the twin, against its ground truth (``equidiff calibrate cameras --twin``)
"""

from .config import TwinConfig, load_twin_config
from .scene import ScenePoses, sample_scene

__all__ = ["ScenePoses", "TwinConfig", "load_twin_config", "sample_scene"]
