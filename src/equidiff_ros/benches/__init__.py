"""Benches that need rclpy (a ROS client drives the nodes), each the body of one ``equidiff bench`` command.

* ``safety_probe``: the ROS side of ``equidiff bench safety`` (its campaign is ``equidiff_core.benches.safety``).
"""
