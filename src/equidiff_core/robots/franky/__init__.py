"""franky 2.0 backend (PyPI ``franky-control``): a real FR3 or franky-sim at ``ip`` (``make_robot("franky", ...)``).

* ``robot``: ``FrankyRobot`` (streaming impedance tracker, gripper thread, stops and recovery)
* ``config``: ``FrankyConfig`` (control.yaml's ``franky:`` section)
* ``sim``: franky-sim servers for tests, benches and the twin; ``faults``: fault injection into them
"""

from .config import FrankyConfig
from .robot import FrankyRobot

__all__ = ["FrankyConfig", "FrankyRobot"]
