"""What CPU this is: absolute timings depend on it (one development CPU has AVX-512 with bf16,
another only AVX2), so every benchmark names it beside its figures. How many of its cores are idle,
which sets torch's threads. The precisions a policy computes in, since "auto" picks by machine. And
the calling thread's scheduling policy, which native libraries change behind our back."""

from __future__ import annotations

import contextlib
import logging
import os
import platform
import time

log = logging.getLogger("equidiff.machine")

# The arithmetic a policy trains or infers in. "auto" depends on the machine: bf16 on CUDA, fp32 on a CPU
# (with the encoder on oneDNN, fp32 inference outran bf16 even on a CPU with native bf16: docs/results/model.md,
# "The encoder near the core's limit").
PRECISIONS = ("auto", "fp32", "bf16")


def _cpuinfo() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            return f.read()
    except OSError:  # not Linux
        return ""


def cpu_model() -> str:
    for line in _cpuinfo().splitlines():
        if line.startswith("model name"):
            return line.split(":", 1)[1].strip()
    return platform.processor() or "cpu"


def cpu_flags() -> set[str]:
    for line in _cpuinfo().splitlines():
        if line.startswith("flags"):
            return set(line.split(":", 1)[1].split())
    return set()


def cpu_has_native_bf16() -> bool:
    """AVX512-BF16 or AMX: there bf16 3D convolutions are much faster than fp32 (docs/results/model.md)."""
    return bool({"avx512_bf16", "amx_bf16"} & cpu_flags())


def cpu_description() -> dict:
    """The CPU's name, cores and the instruction sets absolute timings depend on (for a JSON line)."""
    flags = cpu_flags()
    return {"cpu": cpu_model(), "cores": os.cpu_count(), "avx512": "avx512f" in flags, "bf16": cpu_has_native_bf16()}


def idle_cores(samples: int = 10, interval_s: float = 0.002) -> int:
    """Cores no other task is running on right now, at least one: the cores this process may use
    less the mean count of other runnable tasks (/proc/loadavg's fourth field, sampled ``samples``
    times, ``interval_s`` apart); the core count where /proc is missing."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    try:
        runnable = []
        for _ in range(samples):
            with open("/proc/loadavg") as f:
                runnable.append(int(f.read().split()[3].split("/")[0]) - 1)  # less this process
            time.sleep(interval_s)
    except (OSError, ValueError, IndexError):
        return cores
    return max(1, cores - int(sum(runnable) / len(runnable) + 0.5))


def default_threads_to_idle_cores(environ=os.environ) -> int | None:
    """Set ``OMP_NUM_THREADS`` to the idle cores, unless the user set it; call before torch is imported.

    torch starts one OpenMP thread per core, and those threads spin while they wait for each other:
    on a machine busy with something else (a running twin) they fight it for the same cores, and a
    thread per idle core is faster; on a quiet machine all cores are (measured in docs/results/model.md,
    "CPU threads"). The choice is made once, at start: a job that starts on a quiet machine keeps
    all its cores. Returns the count set, or None where the user's value stands.
    """
    if environ.get("OMP_NUM_THREADS"):
        return None
    threads = idle_cores()
    environ["OMP_NUM_THREADS"] = str(threads)
    return threads


@contextlib.contextmanager
def keep_thread_scheduler(library: str):
    """Give the calling thread its scheduling policy back after a call into ``library``.

    Some native libraries move the thread that calls them to SCHED_FIFO whenever they may (root, or
    an RT kernel): libfranka (priority 99, also with ``RealtimeConfig.Ignore`` and already in
    ``Robot()``), and SVT-AV1, the AV1 encoder the LeRobot export uses (through PyAV). The calling
    thread is a node's, a command's or a test runner's main thread: it stayed real-time, and every
    thread and process started from it afterwards inherited SCHED_FIFO. Twin nodes that render or
    voxelise flat out then starved the rest of the machine (CI's main-job smoke test hung with
    franka_node stuck in its home move), and in a process that had exported videos a policy's
    inference thread ran many times slower beside busy ROS executor threads. The library's own threads
    keep whatever it gave them.
    """
    try:
        policy, param = os.sched_getscheduler(0), os.sched_getparam(0)
    except (AttributeError, OSError):  # not Linux
        yield
        return
    try:
        yield
    finally:
        if os.sched_getscheduler(0) != policy:
            try:
                os.sched_setscheduler(0, policy, param)
            except OSError as err:
                log.warning(f"could not restore this thread's scheduling policy after {library}: {err}")
