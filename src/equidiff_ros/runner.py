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

from equidiff_core.runtime.parent_job import job_gone


def run_node(
    name: str,
    usage: str,
    build_node: Callable[[], object],
    startup_errors: tuple[type[BaseException], ...],
    args: Sequence[str] | None = None,
) -> int:
    """Build (``build_node()``: usually the node class) and spin a node; exit 1 with a one-line
    message on an expected start-up error (``startup_errors``: the node's ``STARTUP_ERRORS``), a
    traceback on any other."""
    return run_nodes(name, usage, [build_node], startup_errors, args)


def run_nodes(
    name: str,
    usage: str,
    builders: Sequence[Callable[[], object]],
    startup_errors: tuple[type[BaseException], ...],
    args: Sequence[str] | None = None,
    multithreaded: bool = False,
) -> int:
    """``run_node`` for several nodes in one process (``equidiff_ros.composed``): built in order,
    spun by one executor (a MultiThreadedExecutor with ``multithreaded``, so a slow callback of
    one node does not hold up the others), shut down newest first."""
    argv = sys.argv[1:] if args is None else list(args)
    if "-h" in argv or "--help" in argv:
        print(usage)
        return 0
    import rclpy
    from rclpy.signals import SignalHandlerOptions

    from equidiff_core.config import ConfigError

    # a config file or parameter the node cannot run with is a start-up error of every node
    startup_errors = (*startup_errors, ConfigError)
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    nodes = []
    try:
        try:
            for build in builders:
                nodes.append(build())
        except startup_errors as err:
            print(f"{name}: {err}", file=sys.stderr)
            return 1
        spin_until_signal(nodes, multithreaded)
    except KeyboardInterrupt:  # Ctrl-C during start-up
        pass
    finally:
        for node in reversed(nodes):
            shutdown = getattr(node, "shutdown", None)
            if shutdown is not None:
                shutdown()
            node.destroy_node()
        if rclpy.ok():
            rclpy.try_shutdown()
    return 0


def spin_until_signal(nodes, multithreaded: bool = False) -> None:
    """Spin ``nodes`` (one node or a list) until SIGINT/SIGTERM or until the job that started
    them died (then return, leaving the context up)."""
    from rclpy.executors import MultiThreadedExecutor, SingleThreadedExecutor

    nodes = list(nodes) if isinstance(nodes, (list, tuple)) else [nodes]
    stop = threading.Event()
    previous = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in (signal.SIGINT, signal.SIGTERM)}
    executor = MultiThreadedExecutor() if multithreaded else SingleThreadedExecutor()
    for node in nodes:
        executor.add_node(node)
    try:
        while not stop.is_set():
            executor.spin_once(timeout_sec=0.1)
            if job_gone():
                names = ", ".join(n.get_name() for n in nodes)
                them = "this node" if len(nodes) == 1 else "these nodes"
                print(f"{names}: the job that started {them} is gone; shutting down", file=sys.stderr)
                break
    finally:
        executor.shutdown(timeout_sec=1.0)  # first: no callback may still run while the nodes go
        for node in nodes:
            executor.remove_node(node)
        for sig, handler in previous.items():
            signal.signal(sig, handler)
