"""Shared fixtures. Area-specific helpers live in test/helpers_*.py, not here."""

import os

import pytest
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
