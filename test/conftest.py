"""Shared fixtures. Area-specific helpers live in test/helpers_*.py, not here."""

import os
import time

import pytest
import torch
from helpers_ros import private_test_domain

os.environ.setdefault("MUJOCO_GL", "egl")


@pytest.fixture
def ros_domain(monkeypatch) -> int:
    """A private ROS_DOMAIN_ID for this test, on loopback only, inherited by spawned nodes."""
    domain = private_test_domain(os.getpid() * 1000 + id(monkeypatch))
    monkeypatch.setenv("ROS_DOMAIN_ID", str(domain))
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    return domain


@pytest.fixture(autouse=True)
def _runner_stays_time_shared():
    """No test may leave the runner's thread real-time. Native libraries (libfranka, SVT-AV1) make the
    thread that calls them SCHED_FIFO when they may (root); every later thread and node process the
    runner starts would inherit it and the rest of the suite would crawl, far from the test at fault."""
    before = os.sched_getscheduler(0) if hasattr(os, "sched_getscheduler") else None
    yield
    if before is not None:
        assert os.sched_getscheduler(0) == before, "this test left the test runner's thread real-time"


def idle_cores(samples: int = 10, interval_s: float = 0.002) -> int:
    """Cores no other task is running on right now: the cores less the mean count of runnable tasks
    besides this one (/proc/loadavg's fourth field, sampled ``samples`` times); the core count where
    /proc is missing."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    try:
        runnable = []
        for _ in range(samples):
            with open("/proc/loadavg") as f:
                runnable.append(int(f.read().split()[3].split("/")[0]) - 1)  # less this process
            time.sleep(interval_s)
    except (OSError, ValueError, IndexError):
        return cores
    return cores - int(sum(runnable) / len(runnable) + 0.5)


@pytest.fixture(autouse=True)
def _torch_threads_on_idle_cores():
    """In-process torch gets one thread per idle core, at least one. Its OpenMP threads spin while
    they wait for each other, so on a busy machine two threads on two cores ran a test 2.6x slower
    than one (`check equivariance` beside a running twin: 84 s against 32 s), while on a quiet
    machine two were 1.5x faster than one (the two-demo over-fit: 64 s against 97 s)."""
    torch.set_num_threads(max(1, idle_cores()))
