"""Spawning and stopping node processes in ROS tests (inherits the test's ROS_DOMAIN_ID)."""

import os
import signal
import subprocess
import sys


def spawn_node(module: str, *params: str) -> subprocess.Popen:
    """``python -m equidiff_ros.<module> --ros-args -p k:=v ...`` with output captured."""
    args = [sys.executable, "-m", f"equidiff_ros.{module}", "--ros-args"]
    for p in params:
        args += ["-p", p]
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1")
    return subprocess.Popen(args, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def stop_node(proc: subprocess.Popen, sig=signal.SIGINT) -> str:
    """Signal, wait up to 10 s, kill if needed; return everything the node printed."""
    if proc.poll() is None:
        proc.send_signal(sig)
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    return proc.stdout.read() if proc.stdout else ""
