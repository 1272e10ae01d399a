"""The lab's people in the loop, ROS-free: the operator's screen logic and the SpaceMouse.

* ``node_view``: what the lab's nodes publish, as the operator loop and ``equidiff lab status`` read it
* ``operator_loop``: the operator loop of ``equidiff lab`` (what the screen shows, what each key does)
* ``teleop``: SpaceMouse teleoperation, a 6-D twist + buttons -> an absolute TCP target and gripper width
"""
