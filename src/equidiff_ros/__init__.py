"""Thin rclpy nodes wiring equidiff_core objects to ROS 2 topics.

Importing this package does not import rclpy: node modules do, so the `equidiff` CLI's
offline commands work without ROS.
"""
