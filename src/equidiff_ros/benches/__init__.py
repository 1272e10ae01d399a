"""Benches that need rclpy (a ROS client drives the nodes), each the body of one ``equidiff bench`` command.

* ``control``: the franka node on franky-sim: tracking, hold, workspace, NaN chunks and policy latency.
* ``safety_probe``: the ROS side of ``equidiff bench safety`` (its campaign is ``equidiff_core.benches.fault_campaign``).
* ``twin``: where the twin's CPU goes, each process's share and wall seconds per sim second.
"""
