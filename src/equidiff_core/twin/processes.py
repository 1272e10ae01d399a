"""Separate node processes for the twin's jobs, on a private ROS domain, always shut down cleanly.

Each node runs in its own session (so a terminal Ctrl-C reaches only the orchestrator, which
then stops the nodes in reverse start order: SIGINT, then SIGTERM, then SIGKILL after a grace
period). stdout/stderr of each node go to ``<log_dir>/<name>.log``; a node that dies early is
reported with the tail of its log.
"""

from __future__ import annotations

import os
import random
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Self

from ..runtime.parent_job import PARENT_PID_ENV


class NodeProcessError(RuntimeError):
    """A node could not be started or died while it was needed."""


def random_domain_id() -> int:
    """A ROS_DOMAIN_ID for a job of its own: 101-215, clear of the usual 0-100 (and of the
    tests' own, chosen the same way) and within the 0-232 Fast DDS allows."""
    return random.SystemRandom().randint(101, 215)


def private_ros_env(domain_id: int | None = None, **extra: str) -> dict[str, str]:
    """The environment for the job's processes: a ROS domain of its own on loopback only."""
    env = dict(os.environ)
    if domain_id is None:
        domain_id = random_domain_id()
    env.update(
        {
            "ROS_DOMAIN_ID": str(domain_id),
            "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
            "MUJOCO_GL": env.get("MUJOCO_GL", "egl"),
            "PYTHONUNBUFFERED": "1",
            # rcutils block-buffers log lines into a file: a killed node lost its last minute of logs
            "RCUTILS_LOGGING_BUFFERED_STREAM": "0",
        }
    )
    env.update({k: str(v) for k, v in extra.items()})
    return env


def join_private_domain(domain_id: int | None = None) -> int:
    """Put this process on a private loopback ROS domain (``domain_id``; else the one already in
    the environment, else a random one) before it starts rclpy: the benches that start nodes."""
    if domain_id is not None:
        os.environ["ROS_DOMAIN_ID"] = str(domain_id)
    elif "ROS_DOMAIN_ID" not in os.environ:
        os.environ["ROS_DOMAIN_ID"] = str(random_domain_id())
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    return int(os.environ["ROS_DOMAIN_ID"])


def node_command(executable: str, params: dict | None = None, remaps: dict | None = None) -> list[str]:
    """``<exe> --ros-args -p k:=v ... -r from:=to``; uses the entry point or ``python -m`` if not on PATH."""
    exe = shutil.which(executable)
    cmd = [exe] if exe else [sys.executable, "-m", f"equidiff_ros.{executable}"]
    if params or remaps:
        cmd.append("--ros-args")
        for k, v in (params or {}).items():
            cmd += ["-p", f"{k}:={_param_text(v)}"]
        for a, b in (remaps or {}).items():
            cmd += ["-r", f"{a}:={b}"]
    return cmd


def _param_text(value) -> str:
    """A ``-p`` value as ROS should read it. ROS parses the text as YAML: a string that YAML reads
    as a mapping or a list (``backend_options``: '{width: 424}') or nothing ('') is quoted; a
    number written as a string ('100.0') stays a number, as callers mean it."""
    import yaml

    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str) and (value == "" or isinstance(yaml.safe_load(value), (dict, list))):
        return "'" + value.replace("'", "''") + "'"
    return str(value)


def composed_command(
    nodes: dict[str, dict],
    params_file: Path,
    remaps: dict[str, dict] | None = None,
    kinds: dict[str, str] | None = None,
) -> list[str]:
    """One process running several nodes (``equidiff_ros.composed``): each node's parameters
    written under its name to ``params_file`` (ROS 2's parameter-file format), each remap
    prefixed with the node it is meant for. ``kinds``: name -> executable for a node not named
    after its executable (one camera_node per camera)."""
    import yaml

    params_file = Path(params_file)
    params_file.parent.mkdir(parents=True, exist_ok=True)
    params_file.write_text(yaml.safe_dump({name: {"ros__parameters": p} for name, p in nodes.items()}, sort_keys=False))
    exe = shutil.which("equidiff_composed")
    cmd = [exe] if exe else [sys.executable, "-m", "equidiff_ros.composed"]
    kinds = kinds or {}
    spec = [f"{name}={kinds[name]}" if kinds.get(name, name) != name else name for name in nodes]
    cmd += ["--nodes", ",".join(spec), "--ros-args", "--params-file", str(params_file)]
    for node, node_remaps in (remaps or {}).items():
        for a, b in node_remaps.items():
            cmd += ["-r", f"{node}:{a}:={b}"]
    return cmd


def start_node(
    executable: str,
    params: dict | None = None,
    log_path: Path | None = None,
    priority: bool = False,
    remaps: dict | None = None,
    env: dict[str, str] | None = None,
    capture: bool = False,
) -> subprocess.Popen:
    """One node process, the way every node is started (``ProcessGroup.start``, the benches, the
    tests): ``node_command`` with ``node_preexec``; output to ``log_path`` (default: discarded) or,
    with ``capture``, to a text pipe the caller reads."""
    cmd = node_command(executable, params, remaps)
    env = {**(os.environ if env is None else env), "PYTHONUNBUFFERED": "1"}
    if capture:
        return subprocess.Popen(
            cmd,
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            stdin=subprocess.DEVNULL,
            preexec_fn=node_preexec(priority),
        )
    with open(log_path or os.devnull, "wb") as out:  # the child keeps its own copy of the descriptor
        return subprocess.Popen(
            cmd,
            env=env,
            stdout=out,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            preexec_fn=node_preexec(priority),
        )


def stop_process(proc: subprocess.Popen | None, timeout: float = 10.0, sig: int = signal.SIGINT) -> int | None:
    """Signal ``proc``, wait up to ``timeout`` s, kill it if it is still there; its exit code."""
    if proc is None:
        return None
    if proc.poll() is None:
        proc.send_signal(sig)
        try:
            proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    return proc.returncode


@dataclass
class NodeProcess:
    name: str
    cmd: list[str]
    popen: subprocess.Popen
    log: Path

    def alive(self) -> bool:
        return self.popen.poll() is None

    def log_tail(self, n: int = 15) -> str:
        try:
            return "\n".join(self.log.read_text(errors="replace").splitlines()[-n:])
        except OSError:
            return "(no log)"


class ProcessGroup:
    """Start nodes, watch them, stop them all (context manager; also on SIGTERM)."""

    def __init__(self, env: dict[str, str], log_dir: Path, grace_s: float = 6.0, servers: tuple[str, ...] = ()):
        """``servers``: the names of nodes the others connect to (twin_node: franky-sim and the cameras'
        shared memory), stopped after all the others."""
        self.env = env
        self.servers = servers
        self.log_dir = Path(log_dir)
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.grace_s = grace_s
        self.nodes: list[NodeProcess] = []
        self._old_sigterm = None

    def start(self, name: str, cmd: list[str], priority: bool = False) -> NodeProcess:
        """Start a node; ``priority``: a higher CPU priority when permitted (the franka node, which
        a robot PC runs on a real-time kernel: starved on a loaded machine, its 1 kHz loop slows the twin)."""
        log = self.log_dir / f"{name}.log"
        # the node shuts itself down if this process dies without stopping it (equidiff_ros.runner)
        env = {**self.env, PARENT_PID_ENV: str(os.getpid())}
        with open(log, "wb") as fh:
            popen = subprocess.Popen(
                cmd,
                env=env,
                stdout=fh,
                stderr=subprocess.STDOUT,
                stdin=subprocess.DEVNULL,
                start_new_session=True,
                preexec_fn=node_preexec(priority),
            )
        node = NodeProcess(name, cmd, popen, log)
        self.nodes.append(node)
        return node

    def check(self) -> None:
        """Raise if any node has exited (they are all meant to run until we stop them)."""
        for node in self.nodes:
            if not node.alive():
                raise NodeProcessError(
                    f"{node.name} exited with code {node.popen.returncode}; "
                    f"last lines of {node.log}:\n{node.log_tail()}"
                )

    def stop(self, name: str) -> None:
        for node in [n for n in self.nodes if n.name == name]:
            self._stop([node])
            self.nodes.remove(node)

    def stop_all(self) -> None:
        # a client (franka_node) must leave before its server (twin_node): the clients together (each takes
        # up to a second or two to shut down), then the servers one at a time, newest first
        self._stop([n for n in self.nodes if n.name not in self.servers])
        for node in reversed([n for n in self.nodes if n.name in self.servers]):
            self._stop([node])
        self.nodes.clear()

    def _stop(self, nodes: list[NodeProcess]) -> None:
        for sig, wait in ((signal.SIGINT, self.grace_s), (signal.SIGTERM, 3.0), (signal.SIGKILL, 2.0)):
            live = [n for n in nodes if n.alive()]
            if not live:
                return
            for n in live:
                try:
                    os.killpg(n.popen.pid, sig)  # the node and anything it spawned
                except ProcessLookupError:
                    pass
            deadline = time.monotonic() + wait
            for n in live:
                try:
                    n.popen.wait(timeout=max(0.0, deadline - time.monotonic()))
                except subprocess.TimeoutExpired:
                    pass

    def __enter__(self) -> Self:
        def on_term(signum, frame):
            raise KeyboardInterrupt  # unwinds the job through its finally blocks

        try:
            self._old_sigterm = signal.signal(signal.SIGTERM, on_term)
        except ValueError:  # not the main thread
            self._old_sigterm = None
        return self

    def __exit__(self, *exc) -> None:
        self.stop_all()
        if self._old_sigterm is not None:
            signal.signal(signal.SIGTERM, self._old_sigterm)


def cpu_seconds(pid: int) -> float:
    """CPU time (user + system) a live process has used so far, from /proc (Linux)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime, stime


def node_preexec(priority: bool = False):
    """``preexec_fn`` for a node process: always an ordinary time-sharing process, never a
    real-time policy inherited from whoever started it (libfranka had left a test runner's main
    thread at SCHED_FIFO 99, and nodes busy rendering then starved the machine); ``priority``
    adds a raised nice level where permitted."""

    def setup() -> None:
        from ..robots.franky.sim import raise_priority

        try:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
        except (AttributeError, OSError):  # not Linux
            pass
        if priority:
            raise_priority(-5)

    return setup
