"""Shared fixtures. Area-specific helpers live in test/helpers_*.py, not here."""

import os
import random

import pytest

os.environ.setdefault("MUJOCO_GL", "egl")


@pytest.fixture
def ros_domain(monkeypatch) -> int:
    """A private ROS_DOMAIN_ID for this test, on loopback only, inherited by spawned nodes."""
    domain = random.Random(os.getpid() * 1000 + id(monkeypatch)).randint(1, 100)
    monkeypatch.setenv("ROS_DOMAIN_ID", str(domain))
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    return domain
