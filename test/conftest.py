"""Shared fixtures. Area-specific helpers live in test/helpers_*.py, not here."""

import os

import pytest
import torch
from helpers_ros import private_test_domain

from equidiff_core.runtime.machine import idle_cores

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


@pytest.fixture(autouse=True)
def _torch_threads_on_idle_cores(monkeypatch):
    """Each test gets torch threads for the cores idle when it starts, as each `equidiff` command
    does (equidiff_core.runtime.machine.default_threads_to_idle_cores): in process, and through
    OMP_NUM_THREADS in the commands and nodes it starts. The suite runs for many minutes and the load
    beside it changes, so the choice is made again for every test, not once."""
    threads = idle_cores()
    torch.set_num_threads(threads)
    monkeypatch.setenv("OMP_NUM_THREADS", str(threads))
