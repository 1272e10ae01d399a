"""The one `main()` every node shares: --help without starting ROS, clean start-up errors, and
a shutdown that stops hardware before the ROS context goes.

rclpy's default signal handlers shut the context down first, racing whatever the node is
still doing (a franky control loop, an inference worker, a bag writer). Here SIGINT/SIGTERM
only end the spin loop; then ``node.shutdown()`` stops the node's own threads and devices,
and only then is the node destroyed and rclpy shut down.
"""

from __future__ import annotations

import signal
import sys
import threading
from collections.abc import Callable, Sequence


def run_node(name: str, usage: str, build_node: Callable[[], object],
             startup_errors: Callable[[], tuple[type[BaseException], ...]], args: Sequence[str] | None = None) -> int:
    """Build (``build_node()``: usually the node class) and spin a node; exit 1 with a one-line
    message on an expected start-up error (``startup_errors()``: the exception types)."""
    argv = sys.argv[1:] if args is None else list(args)
    if "-h" in argv or "--help" in argv:
        print(usage)
        return 0
    import rclpy
    from rclpy.signals import SignalHandlerOptions

    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    node = None
    try:
        expected = startup_errors()
        try:
            node = build_node()
        except expected as err:
            print(f"{name}: {err}", file=sys.stderr)
            return 1
        spin_until_signal(node)
    except KeyboardInterrupt:  # Ctrl-C during start-up
        pass
    finally:
        if node is not None:
            shutdown = getattr(node, "shutdown", None)
            if shutdown is not None:
                shutdown()
            node.destroy_node()
        if rclpy.ok():
            rclpy.try_shutdown()
    return 0


def spin_until_signal(node) -> None:
    """Spin ``node`` until SIGINT/SIGTERM or until the job that started it died (then return,
    leaving the context up)."""
    from rclpy.executors import SingleThreadedExecutor

    from equidiff_core.twin.processes import job_gone

    stop = threading.Event()
    previous = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in (signal.SIGINT, signal.SIGTERM)}
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    try:
        while not stop.is_set():
            executor.spin_once(timeout_sec=0.1)
            if job_gone():
                print(f"{node.get_name()}: the job that started this node is gone; shutting down", file=sys.stderr)
                break
    finally:
        executor.remove_node(node)
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def declare_number(node, name: str, default: float) -> float:
    """A positive float parameter that also accepts integers on the command line (-p rate_hz:=5)."""
    from rcl_interfaces.msg import ParameterDescriptor

    value = node.declare_parameter(name, float(default), ParameterDescriptor(dynamic_typing=True)).value
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not value > 0:
        raise ValueError(f"parameter {name} must be a positive number, got {value!r}")
    return float(value)
