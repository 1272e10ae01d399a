"""Torch's threads follow the idle cores: a command started on a busy machine must not spin OpenMP
threads against the work already running there (a twin), and a user's OMP_NUM_THREADS stands."""

import os
import subprocess
import sys
import time

import pytest

from equidiff_core.runtime.machine import default_threads_to_idle_cores, idle_cores
from equidiff_ros.cli import main


@pytest.fixture
def every_core_busy():
    """One busy process per core, running before the test body starts."""
    cores = len(os.sched_getaffinity(0))
    hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(cores)]
    try:
        deadline = time.monotonic() + 10
        while idle_cores() > 1 and time.monotonic() < deadline:
            time.sleep(0.05)
        yield cores
    finally:
        for hog in hogs:
            hog.kill()
            hog.wait()


def test_a_machine_busy_on_every_core_has_one_idle_core_left_for_torch(every_core_busy):
    environ: dict[str, str] = {}
    assert default_threads_to_idle_cores(environ) == 1
    assert environ == {"OMP_NUM_THREADS": "1"}


def test_idle_cores_never_exceeds_the_cores_this_process_may_use():
    assert 1 <= idle_cores() <= len(os.sched_getaffinity(0))


def test_the_users_own_thread_count_stands():
    environ = {"OMP_NUM_THREADS": "3"}
    assert default_threads_to_idle_cores(environ) is None
    assert environ == {"OMP_NUM_THREADS": "3"}


def test_a_command_started_on_a_busy_machine_gives_torch_one_thread(every_core_busy, monkeypatch, capsys):
    """The CLI chooses before the command imports torch, and torch takes the choice."""
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    assert main(["bench", "overfit", "--steps", "0"]) == 2  # refused before anything is built
    assert os.environ["OMP_NUM_THREADS"] == "1"
    torch_threads = subprocess.run(
        [sys.executable, "-c", "import torch; print(torch.get_num_threads())"],
        capture_output=True,
        text=True,
        check=True,
        timeout=120,
    ).stdout
    assert torch_threads.strip() == "1"
