"""Spawning and stopping node processes in ROS tests (inherits the test's ROS_DOMAIN_ID)."""

import os
import random
import signal
import subprocess


def private_test_domain(seed: int) -> int:
    """A ROS_DOMAIN_ID for a test's nodes, drawn from 1-100: clear of the jobs' 101-215
    (``processes.random_domain_id``: a twin running beside the suite) and of the test stacks' 221-232.
    Two stacks in one domain would command each other's robot."""
    return random.Random(seed).randint(1, 100)


def spawn_node(module: str, *params: str) -> subprocess.Popen:
    """The node ``module`` started the project's one way (``processes.start_node``), with
    ``k:=v`` parameters and its output captured."""
    import yaml

    from equidiff_core.twin.processes import start_node

    # ROS reads a -p value as YAML: read it the same way, so start_node gets the typed value
    values = {key: yaml.safe_load(text) if text else "" for key, text in (p.split(":=", 1) for p in params)}
    return start_node(module, values, env=dict(os.environ, OMP_NUM_THREADS="1"), capture=True)


def stop_node(proc: subprocess.Popen, sig=signal.SIGINT) -> str:
    """Signal, wait up to 10 s, kill if needed; return everything the node printed."""
    from equidiff_core.twin.processes import stop_process

    stop_process(proc, timeout=10.0, sig=sig)
    return proc.stdout.read() if proc.stdout else ""


def run_job(args: list[str], timeout_s: float, env: dict, log_dir) -> subprocess.CompletedProcess:
    """Run an `equidiff ...` job to completion, never hanging the test run.

    Output goes to files, not pipes (a pipe is held open by anything the job left running). On
    timeout the job prints its threads' stacks (SIGUSR1, cli.main), gets SIGTERM (it stops its
    nodes) and, 60 s later, its whole session is killed; returncode is then -9/-15 and the
    stacks are in stderr.
    """
    import time
    from pathlib import Path

    log_dir = Path(log_dir)
    log_dir.mkdir(parents=True, exist_ok=True)
    out_path, err_path = log_dir / "job.stdout", log_dir / "job.stderr"
    with open(out_path, "wb") as out, open(err_path, "wb") as err:
        proc = subprocess.Popen(args, env=env, stdout=out, stderr=err, stdin=subprocess.DEVNULL, start_new_session=True)
    try:
        proc.wait(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        for sig, grace in ((signal.SIGUSR1, 2.0), (signal.SIGTERM, 60.0), (signal.SIGKILL, 10.0)):
            try:
                os.killpg(proc.pid, sig)
            except ProcessLookupError:
                break
            try:
                proc.wait(timeout=grace)
                if sig != signal.SIGUSR1:
                    break
            except subprocess.TimeoutExpired:
                pass
        time.sleep(0.5)
    return subprocess.CompletedProcess(
        args, proc.returncode, out_path.read_text(errors="replace"), err_path.read_text(errors="replace")
    )


class FrozenMainThread:
    """Freeze one process's main thread (ptrace), leaving its other threads running: a node whose
    Python hangs while its DDS threads live on, as a real hang does.

    SIGSTOP stops every thread, DDS's included, and a stopped participant can stall its peers' DDS
    traffic (docs/architecture.md, topic note 6): the twin then stalled on voxel_node or franka_node,
    not on the hung node. The tracer must stay in the thread that froze it."""

    _SEIZE, _INTERRUPT, _DETACH, _WALL = 0x4206, 0x4207, 17, 0x40000000

    def __init__(self, pid: int):
        import ctypes

        self.pid = pid
        self._libc = ctypes.CDLL(None, use_errno=True)
        self._libc.ptrace.argtypes = [ctypes.c_long, ctypes.c_long, ctypes.c_void_p, ctypes.c_void_p]

    def _ptrace(self, request: int) -> None:
        import ctypes

        if self._libc.ptrace(request, self.pid, None, None) == -1:
            errno = ctypes.get_errno()
            raise OSError(errno, f"ptrace({request:#x}) on {self.pid}: {os.strerror(errno)}")

    def __enter__(self):
        self._ptrace(self._SEIZE)
        try:
            self._ptrace(self._INTERRUPT)
            os.waitpid(self.pid, self._WALL)  # until the thread is stopped
        except BaseException:
            self._ptrace(self._DETACH)  # never leave the node traced when the freeze failed
            raise
        return self

    def __exit__(self, *exc) -> None:
        self._ptrace(self._DETACH)
