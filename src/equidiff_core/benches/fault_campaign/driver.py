"""The campaign of ``equidiff bench safety`` (the command's help says what each fault does and what
surviving it means): franky-sim with the twin's scene, franka_node and recorder_node started, the
start-up hold acknowledged as the operator, the baseline drift measured, then one fault at a time, the
arm home between them; one JSON line's content.
"""

from __future__ import annotations

import json
import logging
import os
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from equidiff_core.benches.fault_campaign import chunk_faults, node_faults, stop_faults
from equidiff_core.benches.fault_campaign.campaign import Campaign, Probe, start_episode, start_franka, stop_episode
from equidiff_core.benches.fault_campaign.report import campaign_summary
from equidiff_core.config import default_config_dir, dump_yaml, load_lab_config, load_mapping
from equidiff_core.control import load_control_config
from equidiff_core.robots.franky.sim import SimServer
from equidiff_core.runtime.jobs import JobError
from equidiff_core.runtime.machine import cpu_description
from equidiff_core.runtime.output_files import staged_dir
from equidiff_core.twin.processes import join_private_domain, start_node, stop_process
from equidiff_core.twin.standin import STANDIN_LABEL, make_standin_policy

logger = logging.getLogger(__name__)

# each fault's run, in the campaign's order; the policy faults also take the camera pipeline
FAULT_RUNS: dict[str, Callable[..., dict]] = {
    "nan": chunk_faults.fault_nan,
    "jump": chunk_faults.fault_jump,
    "stale_chunk": chunk_faults.fault_stale_chunk,
    "out_of_box": chunk_faults.fault_out_of_box,
    "out_of_cone": chunk_faults.fault_out_of_cone,
    "user_stop": stop_faults.fault_user_stop,
    "reflex": stop_faults.fault_reflex,
    "connection_lost": stop_faults.fault_connection_lost,
    "divergence": stop_faults.fault_divergence,
    "camera_stall": node_faults.fault_camera_stall,
    "policy_node_killed": node_faults.fault_policy_node_killed,
    "recorder_sigkill": node_faults.fault_recorder_sigkill,
    "gripper_stuck": node_faults.fault_gripper_stuck,
    "franka_node_killed": stop_faults.fault_franka_node_killed,
}
FAULTS = tuple(FAULT_RUNS)
POLICY_FAULTS = ("camera_stall", "policy_node_killed")
# puts the twin's block and bowl at y > 0.09 m, clear of every approach of out_of_box
SCENE_SEED = 82


def control_config_with_margin(tmp: Path, margin_mm: float | None, path: Path | None = None) -> tuple[Path, object]:
    """``path`` (default control.yaml), or a copy of it with ``safety.box_margin_m`` set (``--box-margin-mm``)."""
    path = Path(path) if path is not None else default_config_dir() / "control.yaml"
    if margin_mm is not None:
        data = load_mapping(path)
        data.setdefault("safety", {})["box_margin_m"] = float(margin_mm) / 1000
        path = tmp / "control.yaml"
        path.write_text(dump_yaml(data))
    return path, load_control_config(path)


def run_campaign(
    faults: list[str],
    tmp: Path,
    probe: Probe,
    still_mm: float = 3.0,
    box_margin_mm: float | None = None,
    log: Callable[[str], None] = lambda _m: None,
    policy: str = "shipped",
    control_config: Path | None = None,
) -> dict:
    """Run ``faults`` (in FAULTS' order) against the graph ``probe`` reaches and return the result dict
    (the JSON line's content)."""
    unknown = sorted(set(faults) - set(FAULTS))
    if unknown:
        raise JobError(f"unknown fault(s) {unknown}; choose from {list(FAULTS)}", 2)
    faults = [f for f in FAULTS if f in faults]
    lab_path = default_config_dir() / "lab.yaml"
    lab = load_lab_config(lab_path)
    control_path, control = control_config_with_margin(tmp, box_margin_mm, control_config)
    wall0 = time.monotonic()
    result: dict = {"machine": cpu_description(), "ros_domain_id": int(os.environ["ROS_DOMAIN_ID"])}
    per_fault: dict = {}
    run_dir = tmp / "run"
    run_dir.mkdir(exist_ok=True)
    shm = f"equidiff_bench_safety_{os.getpid()}"
    # the sim waits up to 0.5 s for franky's command each tick, as the twin on simulated time does: an
    # FR3 never runs on a starved client's stale torque (it stops with a reflex), and the figures
    # here are franka_node's, not the machine's load (which made the overshoot 2-15 mm at 20 ms)
    twin_args = ("--config", str(default_config_dir() / "twin.yaml"), "--shm", shm, "--seed", str(SCENE_SEED))
    twin_args += ("--command-wait-s", "0.5")
    with SimServer(module="equidiff_core.twin.sim", args=twin_args) as sim:
        client = pipe = None
        c = Campaign(
            client=None,
            sim=sim,
            box=lab.safety_box,
            tmp=tmp,
            franka_params={
                "robot_ip": sim.host,
                "realtime": False,
                "lab_config": str(lab_path),
                "control_config": str(control_path),
                "run_dir": str(run_dir),
            },
            still_m=still_mm / 1000,
            box_margin_m=control.safety.box_margin_m,
            shm=sim.ready[0] if sim.ready else shm,
            probe=probe,
        )
        c.home_position = np.asarray(control.home_position)
        c.joint_limits = (control.safety.joint_position_min_rad, control.safety.joint_position_max_rad)
        try:
            c.recorder = start_node(
                "recorder_node",
                {
                    "output_dir": str(tmp / "episodes"),
                    "task": "safety",
                    "min_free_gib": 0.0,
                    "lab_config": str(lab_path),
                },
                tmp / "recorder_node.log",
            )
            client = c.client = probe.open_client(lab, str(lab_path))
            c.status = probe.watch_status(client)
            start_franka(c)  # the lab's defaults: it holds until the operator acknowledges
            c.status.wait(lambda s: s.get("state") == "awaiting_ack", 90.0, "franka_node's start-up hold", c.franka)
            result["start_hold"] = c.status.latest["reason"][:120]
            granted, message = probe.acknowledge()  # as the operator; above the box, it moves home first
            if not granted:
                raise RuntimeError(f"the start-up acknowledgement was refused: {message}")
            c.status.wait(lambda s: s.get("state") == "holding", 60.0, "franka_node holding", c.franka)
            c.home()
            c.t_start = time.time()  # the campaign's excursions count from here: franky-sim starts above the box
            time.sleep(1.0)
            t0 = time.time()
            time.sleep(1.0)
            result["baseline_hold_drift_mm"] = round(c.moved_m(t0, time.time()) * 1000, 3)
            start_episode(c)
            for name in faults:
                if name in POLICY_FAULTS and pipe is None:
                    pipe = node_faults.CameraPipeline(c)
                    checkpoint, result["policy"] = policy_checkpoint(policy, tmp, lab.workspace, probe.shipped_policy())
                    log(f"starting the twin's cameras, voxel_node and policy_node ({result['policy']})")
                    pipe.start(checkpoint)
                if name == "recorder_sigkill" and c.episodes and c.recorder is not None:
                    stop_episode(c)  # keep the first episode; the kill takes the next one
                log(f"fault: {name}")
                t_fault, missed = time.time(), sim.missed_commands()
                fn = FAULT_RUNS[name]
                try:
                    per_fault[name] = fn(c, pipe) if name in POLICY_FAULTS else fn(c)
                except Exception as err:  # noqa: BLE001 - a fault that breaks the campaign is not survived
                    per_fault[name] = {"survived": False, "error": f"{type(err).__name__}: {err}"}
                c.note_excursion(t_fault)
                missed_now = sim.missed_commands()
                if missed is not None and missed_now is not None:
                    # a starved franka_node: the sim ran physics on its last torque (a delayed loop)
                    per_fault[name]["sim_missed_commands"] = missed_now - missed
                if not c.alive():
                    log("franka_node died: restarting it for the remaining faults")
                    start_franka(c)
                elif name in POLICY_FAULTS:
                    if name == POLICY_FAULTS[-1] or not set(POLICY_FAULTS[POLICY_FAULTS.index(name) + 1 :]) & set(
                        faults
                    ):
                        pipe.stop()  # the cameras' rendering costs a core: not beside the remaining faults
                    c.home()  # the policy moved (and yawed) the arm
                log(f"  {json.dumps(per_fault[name])}")
            if c.recorder is not None and c.episodes:
                try:
                    stop_episode(c)
                except probe.ServiceError as err:  # a starved recorder: its SIGINT below still closes the bag
                    log(f"stopping the last episode: {err}")
        finally:
            if pipe is not None:
                pipe.stop()
            if client is not None:
                client.close()
            stop_process(c.recorder)
            result["franka_node_exit_code"] = stop_process(c.franka)
            result["sim_realtime_factor"] = sim.realtime_factor()
            result["sim_missed_commands"] = sim.missed_commands()
    result.update(campaign_summary(c, per_fault, still_mm, control.safety.wall_deceleration_m_s2, wall0))
    return result


def policy_checkpoint(which: str, tmp: Path, workspace, shipped: tuple[Path, str] | None) -> tuple[Path, str]:
    """(checkpoint, label): the ``shipped`` twin policy if asked for and present, else an untrained tiny stand-in."""
    if which == "shipped" and shipped is not None:
        return shipped
    path = tmp / "standin.pt"
    if not path.exists():
        make_standin_policy(path, workspace, preset="tiny", policy="baseline")
    return path, STANDIN_LABEL


def run_bench(
    faults: str,
    probe: Probe,
    still_mm: float = 3.0,
    box_margin_mm: float | None = None,
    policy: str = "shipped",
    control_config: Path | None = None,
    domain_id: int | None = None,
    keep: Path | None = None,
    force: bool = False,
) -> dict:
    """``equidiff bench safety``: ``faults`` comma-separated, on a private ROS domain (``domain_id``), its
    logs and episodes in ``keep`` (default: a temp dir; a new folder, landing when the campaign ends, refused
    if it holds anything unless ``force``); progress through this module's logger; the result (the command's
    JSON line). ``JobError`` (exit status 2) for an unknown fault, before anything starts."""
    join_private_domain(domain_id)
    names = [f.strip() for f in faults.split(",") if f.strip()]
    with staged_dir(keep, force=force, prefix="bench_safety_") as staged:
        return run_campaign(
            names,
            staged.path,
            probe,
            still_mm,
            box_margin_mm,
            log=logger.info,
            policy=policy,
            control_config=control_config,
        )
