"""The ROS side of ``equidiff lab``: one short-lived node that calls the operator services.

Everything goes through services and latched topics, not a node's stdin, so it works the
same under ``ros2 launch`` (where no node has a terminal), over ssh, and in the twin.
"""

from __future__ import annotations

import os
import time

SERVICE_WAIT_S = 5.0
CALL_TIMEOUT_S = 15.0


class LabError(RuntimeError):
    """A service is missing or refused the request."""


def call_service(command: str, srv_type: str, name: str, prefix: str = "", **request) -> int:
    """One ``equidiff lab`` action: call the service, print its answer (``prefix`` first), or
    print why it failed to stderr under ``command``'s name; the exit code."""
    import sys

    with LabClient() as lab:
        try:
            print(f"{prefix}{lab.call(srv_type, name, **request)}")
        except LabError as err:
            print(f"equidiff lab {command}: {err}", file=sys.stderr)
            return 1
    return 0


class LabClient:
    def __init__(self):
        import rclpy
        from rclpy.executors import SingleThreadedExecutor

        self.rclpy = rclpy
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node("equidiff_lab", context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)

    def call(self, srv_type: str, name: str, **request) -> str:
        """Call service ``name``; its message, or LabError with the reason."""
        from equidiff_core.rosmsg import RclpyFactory

        cls = RclpyFactory().cls(srv_type)
        client = self.node.create_client(cls, name)
        try:
            if not client.wait_for_service(timeout_sec=SERVICE_WAIT_S):
                raise LabError(
                    f"no {name} service after {SERVICE_WAIT_S:.0f} s: is its node running on "
                    f"ROS_DOMAIN_ID={os.environ.get('ROS_DOMAIN_ID', '0')}?"
                )
            future = client.call_async(cls.Request(**request))
            self.executor.spin_until_future_complete(future, timeout_sec=CALL_TIMEOUT_S)
            if not future.done():
                raise LabError(f"{name} did not answer within {CALL_TIMEOUT_S:.0f} s")
            response = future.result()
            if not response.success:
                raise LabError(f"{name}: {response.message}")
            return response.message
        finally:
            self.node.destroy_client(client)

    def latched(self, topic: str, msg_type: str, wait_s: float = 5.0):
        """The latched value on ``topic`` (None if nobody publishes it; ``wait_s`` covers discovery on a
        loaded machine, where 2 s once missed a running recorder)."""
        from equidiff_core.rosmsg import RclpyFactory
        from equidiff_ros.common import LATCHED_QOS

        got = []
        sub = self.node.create_subscription(RclpyFactory().cls(msg_type), topic, got.append, LATCHED_QOS)
        try:
            deadline = time.monotonic() + wait_s
            while not got and time.monotonic() < deadline:
                self.executor.spin_once(timeout_sec=0.1)
            return got[-1].data if got else None
        finally:
            self.node.destroy_subscription(sub)

    def close(self):
        self.executor.shutdown()
        self.node.destroy_node()
        self.rclpy.shutdown(context=self.context)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
