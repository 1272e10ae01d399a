"""Benches that need rclpy (a ROS client drives the nodes), each the body of one ``equidiff bench`` command.

* ``control``: the franka node on franky-sim: tracking, hold, workspace, NaN chunks and policy latency.
"""
