"""LeRobot's own interpreter for the export test: a Python 3.12 venv with ``lerobot[dataset]==0.6.1``.

LeRobot 0.5+ needs Python >= 3.12 and torch < 2.12, so it cannot live in the project's venv
(Python 3.11, torch 2.13). The venv is built once, the way LeRobot's docs install it, and
cached outside the repository under a name made of the pinned versions, so only the first run
on a machine pays (measured: 3 min and 5.4 GB on the 2-core Xeon, 2026-11-27, ~10 min when
other work loads the machine; the registry's
x86_64 torch is the CUDA build, whose NVIDIA libraries torch needs to import even on a CPU:
without them ``import torch`` fails on libcudnn.so.9). Later runs reuse it in seconds.

``EQUIDIFF_LEROBOT_VENV`` names another place; ``EQUIDIFF_PYTHON312`` another interpreter.
"""

from __future__ import annotations

import fcntl
import glob
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

LEROBOT_REQUIREMENT = "lerobot[dataset]==0.6.1"
VENV_NAME = "lerobot-0.6.1-py312"


class LeRobotUnavailable(RuntimeError):
    """No Python 3.12 to build LeRobot's venv with."""


def python312() -> Path:
    candidates = [os.environ.get("EQUIDIFF_PYTHON312", "")]
    candidates += sorted(glob.glob("/root/.pyenv/versions/3.12*/bin/python"), reverse=True)
    candidates += [shutil.which("python3.12") or ""]
    for c in candidates:
        if c and Path(c).is_file():
            return Path(c)
    raise LeRobotUnavailable("no Python 3.12 found (set EQUIDIFF_PYTHON312): LeRobot 0.6.1 needs Python >= 3.12")


def venv_dir() -> Path:
    if os.environ.get("EQUIDIFF_LEROBOT_VENV"):
        return Path(os.environ["EQUIDIFF_LEROBOT_VENV"])
    cache = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return cache / "equidiff_ros" / VENV_NAME


def lerobot_python(log=print, timeout_s: float = 1800) -> Path:
    """The venv's interpreter, building the venv first if it is not there (one builder at a time)."""
    venv = venv_dir()
    python = venv / "bin" / "python"
    ready = venv / ".ready"
    if ready.is_file():
        return python
    venv.parent.mkdir(parents=True, exist_ok=True)
    with open(venv.parent / f".{venv.name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # another test process may be building it
        if ready.is_file():
            return python
        base = python312()
        building = venv.with_name(venv.name + ".building")
        shutil.rmtree(building, ignore_errors=True)
        t0 = time.monotonic()
        log(f"building LeRobot's venv {venv} ({LEROBOT_REQUIREMENT}, {base}); once per machine, ~3 min")
        subprocess.run([str(base), "-m", "venv", str(building)], check=True, timeout=120)
        subprocess.run(
            [str(building / "bin" / "python"), "-m", "pip", "install", "-q", LEROBOT_REQUIREMENT],
            check=True,
            timeout=timeout_s,
        )
        shutil.rmtree(venv, ignore_errors=True)
        building.rename(venv)  # venvs are relocatable enough for `bin/python -m ...` (no entry scripts used)
        ready.write_text(f"{LEROBOT_REQUIREMENT} built in {time.monotonic() - t0:.0f} s\n")
        log(ready.read_text().strip())
    return python


if __name__ == "__main__":
    print(lerobot_python())
    sys.exit(0)
