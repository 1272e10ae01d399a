"""The twin jobs' ROS side (``equidiff twin run``, ``twin collect``, ``bench twin``); the twin's
ROS-free logic is ``equidiff_core.twin``, its robot and clock the ``twin_node`` executable.

* ``supervisor``: ``Supervisor``, the jobs' in-process client node (gate, homing, recorder control)
* ``stack``: ``TwinStack``, every node as a process on a private ROS domain, plus the supervisor
* ``world``: ``LiveTwin`` (the episode world), ``GatedPolicy`` and ``LiveExpert`` (its actors),
  ``run_policy_episode``
* ``main_job``: ``equidiff twin run``; ``collect``: ``equidiff twin collect`` (imported by their commands)

Importing it imports rclpy.
"""

from .stack import TwinStack
from .supervisor import Supervisor, SupervisorError
from .world import GatedPolicy, LiveExpert, LiveTwin, run_policy_episode

__all__ = [
    "GatedPolicy",
    "LiveExpert",
    "LiveTwin",
    "Supervisor",
    "SupervisorError",
    "TwinStack",
    "run_policy_episode",
]
