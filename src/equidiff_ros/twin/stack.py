"""The twin stack: every node of the twin as a process on a private ROS domain, plus the supervisor.

What each node is started with is ``equidiff_core.twin.node_specs``; starting, watching and
stopping the processes is ``equidiff_core.twin.processes``.
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Self

from equidiff_core.config import load_lab_config
from equidiff_core.robots.franky.sim import free_loopback_host
from equidiff_core.twin.config import TWIN_PRECISION, load_twin_config
from equidiff_core.twin.expert import tcp_pose
from equidiff_core.twin.node_specs import pipeline_specs, twin_node_params
from equidiff_core.twin.processes import ProcessGroup, composed_command, node_command, private_ros_env
from equidiff_ros.twin.supervisor import Supervisor, SupervisorError

# pipeline nodes that need nothing of twin_node but its /clock
CLOCK_ONLY_NODES = ("policy_node", "voxel_node", "recorder_node")


class TwinStack:
    """All nodes of the twin as separate processes on a private ROS domain, plus the supervisor.

    ``with TwinStack(...) as stack:`` starts twin_node, one camera_node (backend twin) per
    configured camera, voxel_node, franka_node (robot_ip = the twin's loopback address),
    recorder_node and optionally policy_node (its chunks remapped to the supervisor's gate);
    leaving the block (normally, on error, Ctrl-C or SIGTERM) stops them all.

    ``realtime=False`` (the default): twin_node owns the clock (/clock), every other node runs
    with use_sim_time, the cameras take the frames the sim requests and policy chunks take
    effect at their observation's time + ``latency_s``. ``realtime=True``: everything on the
    wall clock, as on a lab machine; only meaningful where the machine holds real time.
    """

    def __init__(
        self,
        out_dir,
        lab_path,
        twin_path,
        policy: str | None = None,
        domain_id: int | None = None,
        task: str = "twin",
        device: str = "cpu",
        precision: str = TWIN_PRECISION,
        seed: int = 0,
        record_clouds: bool = False,
        start_timeout_s: float = 120.0,
        torch_threads: int = 1,
        lenient: bool = False,
        attach: bool = False,
        realtime: bool = False,
        latency_s: float = 0.1,
        stall_timeout_s: float = 30.0,
        max_speed: float = 1.0,
        composed: bool = False,
        policy_parameters: dict | None = None,
        log=print,
    ):
        self.out_dir = Path(out_dir)
        self.lab_path, self.twin_path = Path(lab_path), Path(twin_path)
        self.lab = load_lab_config(self.lab_path)
        self.cfg = load_twin_config(self.twin_path)
        self.policy, self.domain_id, self.task, self.device = policy, domain_id, task, device
        self.precision = precision  # policy_node's
        self.seed, self.record_clouds, self.start_timeout_s = seed, record_clouds, start_timeout_s
        # One thread by default, policy_node's own, on either clock: the sim waits only for a chunk that
        # is due, while the cameras render and the other nodes run beside the inference; beside other load
        # a second thread made inference slower, not faster (docs/results/twin.md: `equidiff bench twin --torch-threads`).
        self.torch_threads = torch_threads
        # lenient: accept older observations (CI machines too loaded to hold 5 Hz); never for reported numbers
        self.lenient = lenient
        self.attach = attach  # nodes started by someone else (launch file): only supervise them
        self.realtime, self.latency_s, self.stall_timeout_s = realtime, latency_s, stall_timeout_s
        self.max_speed = max_speed  # simulated time: at most this many sim seconds per wall second
        self.composed = composed  # every node but twin_node in one process (equidiff_ros.composed)
        self.policy_parameters = policy_parameters  # policy_node's, beside the twin's (e.g. doubt_gate)
        self.log = log
        self.group = None
        self.sup: Supervisor | None = None

    def __enter__(self) -> Self:
        if self.attach:
            self.log(f"[twin] attaching to the running nodes on ROS_DOMAIN_ID={os.environ.get('ROS_DOMAIN_ID', '0')}")
            self.sup = self._supervisor()
            try:
                self.sup.wait_ready(self.start_timeout_s)
                self.sup.wait_for(
                    lambda: self.sup.recorder_status.startswith("idle"), self.start_timeout_s, "recorder_node"
                )
            except BaseException:
                self.__exit__(None, None, None)
                raise
            return self
        env = private_ros_env(self.domain_id, OMP_NUM_THREADS="1", LP_NUM_THREADS="1")
        self.domain_id = int(env["ROS_DOMAIN_ID"])
        env["EQUIDIFF_TWIN_SHM"] = f"equidiff_twin_{self.domain_id}_{os.getpid()}"
        # the supervisor (this process) joins the same private domain
        for key in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE", "EQUIDIFF_TWIN_SHM", "MUJOCO_GL"):
            os.environ[key] = env[key]
        self.host = free_loopback_host()
        self.group = ProcessGroup(env, self.out_dir / "logs", servers=("twin_node",)).__enter__()
        try:
            self._start_nodes()
        except BaseException:
            self.__exit__(None, None, None)
            raise
        return self

    def _supervisor(self) -> Supervisor:
        return Supervisor(
            self.lab.base_frame,
            sim_time=not self.realtime,
            latency_s=self.latency_s,
            stall_timeout_s=self.stall_timeout_s,
        )

    def _start_nodes(self) -> None:
        started = time.monotonic()
        g = self.group
        sim = not self.realtime
        clock = f"simulated time (latency budget {self.latency_s * 1000:.0f} ms)" if sim else "real time"
        self.log(
            f"[twin] ROS_DOMAIN_ID={self.domain_id}; franky-sim on {self.host}; {clock}; logs in {g.log_dir}"
            + ("; the pipeline's nodes in one process" if self.composed else "")
        )
        specs = pipeline_specs(
            self.lab,
            self.lab_path,
            self.out_dir,
            self.host,
            self.task,
            self.record_clouds,
            sim=not self.realtime,
            lenient=self.lenient,
            latency_s=self.latency_s,
            policy=self.policy,
            device=self.device,
            precision=self.precision,
            torch_threads=self.torch_threads,
            policy_parameters=self.policy_parameters,
        )
        # The nodes that need nothing of twin_node but /clock start first, so that their start-up (imports;
        # policy_node loads and warms up its checkpoint before it waits for /clock) overlaps twin_node's
        # instead of competing with the running sim's cameras. The others connect to franky-sim or read
        # the cameras' shared memory: they start once twin_node serves.
        early = [] if self.composed else [name for name in specs if specs[name][0] in CLOCK_ONLY_NODES]
        for name in early:
            self._start_pipeline_node(name, specs.pop(name))
        g.start(
            "twin_node",
            node_command(
                "twin_node",
                twin_node_params(
                    self.lab_path,
                    self.twin_path,
                    self.host,
                    self.seed,
                    sim,
                    self.latency_s,
                    self.stall_timeout_s,
                    self.max_speed,
                ),
            ),
        )
        self.sup = self._supervisor()
        self.sup.wait_for(
            lambda: self.sup.twin_state is not None, self.start_timeout_s, "twin_node's /twin/state", g.check
        )
        if self.composed:
            g.start(
                "pipeline",
                composed_command(
                    {name: params for name, (_kind, params, _remaps) in specs.items()},
                    self.out_dir / "logs" / "pipeline_params.yaml",
                    {name: remaps for name, (_kind, _params, remaps) in specs.items() if remaps},
                    kinds={name: kind for name, (kind, _params, _remaps) in specs.items()},
                ),
                priority=True,
            )  # franka_node is in it
        else:
            for name, spec in specs.items():
                self._start_pipeline_node(name, spec)
        self.sup.wait_ready(self.start_timeout_s, g.check)
        self.sup.wait_for(
            lambda: self.sup.recorder_status.startswith("idle"), self.start_timeout_s, "recorder_node", g.check
        )
        if self.policy:  # an episode must not owe chunks to a policy still loading its checkpoint
            self.sup.wait_for(
                lambda: self.sup.policy_chunks_seen > 0,
                self.start_timeout_s,
                "policy_node's first chunk (loading and warming up the policy)",
                g.check,
            )
        self.log(f"[twin] all nodes up in {time.monotonic() - started:.1f} s")

    def _start_pipeline_node(self, name: str, spec) -> None:
        kind, params, remaps = spec
        named = remaps if name == kind else {**remaps, "__node": name}  # its node name, as in twin.launch.py
        self.group.start(name, node_command(kind, params, named), priority=name == "franka_node")

    def __exit__(self, *exc) -> None:
        try:
            if self.sup is not None and self.sup.recorder_status.startswith("recording"):
                try:  # keep what was recorded, marked as interrupted
                    self.sup.recorder("stop failure interrupted", "idle", timeout_s=5.0)
                except SupervisorError:
                    pass
        finally:
            if self.group is not None:
                stopping = time.monotonic()
                self.group.__exit__(*exc)
                self.group = None
                self.log(f"[twin] all nodes stopped in {time.monotonic() - stopping:.1f} s")
            if self.sup is not None:
                self.sup.close()
                self.sup = None

    def check(self) -> None:
        if self.group is not None:
            self.group.check()

    def home(self) -> None:
        """Move to the ready pose; first acknowledge a stop franka_node holds for, saying so."""

        stopped = self.sup.acknowledge_stop(check=self.check)
        if stopped:
            print(
                f"[twin] franka_node held after '{stopped}'; acknowledged (as the operator) before homing", flush=True
            )
        ex = self.cfg.expert
        try:
            self.sup.move_to(
                tcp_pose(ex.ready_position, 0.0),
                ex.open_width,
                speed=ex.speed,
                timeout_s=self.cfg.episode.home_timeout_s,
                check=self.check,
            )
        except SupervisorError as err:  # the arm or the gripper did not follow: franka_node's log says why
            franka = next((n for n in self.group.nodes if n.name == "franka_node"), None)
            if franka is None:
                raise
            raise SupervisorError(f"{err}\nlast lines of {franka.log}:\n{franka.log_tail()}") from err
