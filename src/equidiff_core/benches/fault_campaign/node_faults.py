"""The faults around franka_node (``equidiff bench safety``): the twin's cameras -> voxel_node ->
policy_node driving the arm, with a camera stalled and the policy killed; recorder_node killed
mid-episode (the episode readable after repair); and franky-sim's gripper jammed while the arm moves.
"""

from __future__ import annotations

import json
import signal
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from equidiff_core.benches.fault_campaign.campaign import Campaign, franka_log, start_episode
from equidiff_core.data.bags import read_episode, repair_bag
from equidiff_core.data.mcap_reader import BagError
from equidiff_core.twin.processes import start_node, stop_process
from equidiff_core.wire.rosmsg import gripper_width_from_joint_state

STALL_S = 5.0  # how long camera_stall stalls a camera


@dataclass
class CameraPipeline:
    """The twin's cameras (one camera_node each, backend twin, rendering the sim's state) ->
    voxel_node -> policy_node -> franka_node: what the policy faults act on."""

    c: Campaign
    cameras: dict = field(default_factory=dict)  # name -> Popen
    voxel: object = None
    policy: object = None
    accepted_before: int = 0  # franka_node's accepted_chunks when the policy started

    def start(self, checkpoint: Path) -> None:
        c, lab_path = self.c, self.c.client.lab_path
        for cam in c.client.lab.cameras:
            self.cameras[cam.name] = start_node(
                "camera_node",
                {
                    "lab_config": lab_path,
                    "backend": "twin",
                    "camera": cam.name,
                    "backend_options": json.dumps({"shm_name": c.shm, "stall_flag": str(self.stall_flag(cam.name))}),
                },
                c.tmp / f"camera_{cam.name}.log",
            )
        # the twin supervisor's lenient matching on real time (its cameras share 2 loaded cores)
        # lenient on a loaded machine (clouds came 2-5 s apart at load 20); a stalled camera still
        # stops the sets: its newest cloud is then never within slop_s of the others'
        self.voxel = start_node(
            "voxel_node", {"lab_config": lab_path, "slop_s": 0.15, "stale_after_s": 10.0}, c.tmp / "voxel_node.log"
        )
        self.accepted_before = c.diag("accepted_chunks")
        self.policy = start_node(
            "policy_node",
            {
                "checkpoint": str(checkpoint),
                "precision": "fp32",
                "lab_config": lab_path,
                "start_paused": False,
                "max_observation_age_s": 8.0,
                # the execution horizon's latency budget: a chunk carries up to all 16 steps, so one
                # answering a seconds-old observation on a loaded CPU still has live steps
                "latency_s": 2.0,
                "max_state_offset_s": 0.5,
            },
            c.tmp / "policy_node.log",
        )
        n0 = len(c.client.data.chunks)
        c.client.wait_for(lambda: len(c.client.data.chunks) > n0, 600.0, "policy_node's first chunk", self.policy)

    def stall_flag(self, camera: str) -> Path:
        """While this file exists, ``camera`` delivers no frames (the twin backend's ``stall_flag``)."""
        return self.c.tmp / f"stall_{camera}"

    def chunks_observed_after(self, t0: float) -> int:
        """Chunks answering an observation (their stamp) later than ``t0``."""
        return sum(stamp > t0 for _, stamp in list(self.c.client.data.chunks))

    def chunks_between(self, t0: float, t1: float) -> int:
        """Chunks received in [t0, t1] (wall clock, s)."""
        return sum(t0 <= r <= t1 for r, _ in list(self.c.client.data.chunks))

    def stop(self) -> None:
        for proc in [self.policy, self.voxel, *self.cameras.values()]:
            stop_process(proc)


def fault_camera_stall(c: Campaign, pipe: CameraPipeline) -> dict:
    time.sleep(5.0)  # the policy acting for a while first
    accepted = c.diag("accepted_chunks") - pipe.accepted_before
    name = next(iter(pipe.cameras))
    # The camera's reads time out, as over a stalled USB link, while its node and DDS live on: a
    # SIGSTOPped node would stall its peers' DDS traffic too (docs/architecture.md, topic note 6).
    flag = pipe.stall_flag(name)
    flag.touch()
    # a frame whose read began just before is stamped at most one period (5 Hz) later and may
    # still complete one set
    t_stall = time.time() + 0.3
    try:
        time.sleep(STALL_S)
    finally:
        t_end = time.time()
        flag.unlink()
    held = c.moved_m(t_end - 1.0, t_end)  # the last chunk's plan has run out by then: the watchdog holds
    try:
        c.client.wait_for(lambda: pipe.chunks_observed_after(t_end) > 0, 60.0, "policy chunks again", pipe.policy)
        again = True
    except (TimeoutError, RuntimeError):
        again = False
    # an inference already running may still answer a grid from before the stall: only chunks for
    # grids stamped during the stall count (there are none to answer), counted once chunks came again
    during = pipe.chunks_observed_after(t_stall) - pipe.chunks_observed_after(t_end)
    c.note_excursion(t_stall)
    return {
        "survived": during == 0 and held < c.still_m and again and c.alive(),
        "stalled_camera": name,
        "policy_chunks_accepted": accepted,
        "chunks_during_stall": during,
        "moved_while_stalled_mm": round(held * 1000, 2),
        "chunks_after_stall": again,
    }


def fault_policy_node_killed(c: Campaign, pipe: CameraPipeline) -> dict:
    holds = c.diag("watchdog_holds")
    t_kill = time.time()
    pipe.policy.send_signal(signal.SIGKILL)
    pipe.policy.wait(timeout=10)
    time.sleep(3.5)
    t_end = time.time()
    after = pipe.chunks_between(t_kill + 0.5, t_end)
    held = c.moved_m(t_end - 1.0, t_end)
    watchdog = c.wait_diag("watchdog_holds", holds, timeout=3.0)
    c.note_excursion(t_kill)
    return {
        "survived": after == 0 and held < c.still_m and c.alive(),
        "chunks_after_kill": after,
        "watchdog_fired_after_kill": watchdog,
        "moved_after_kill_mm": round(held * 1000, 2),
    }


def fault_recorder_sigkill(c: Campaign) -> dict:
    if c.recorder is None or c.recorder.poll() is not None:
        return {"survived": False, "error": "recorder_node is not running"}
    episode = start_episode(c)
    t0 = time.time()
    c.follow_me(2.0, direction=(0.0, 1.0, 0.0))  # the arm moves while recording
    c.recorder.send_signal(signal.SIGKILL)
    c.recorder.wait(timeout=10)
    c.recorder = None
    moved = c.moved_m(t0, time.time())
    try:
        report = repair_bag(episode)
        poses = read_episode(episode, ["/franka/ee_pose"]).message_counts.get("/franka/ee_pose", 0)
        readable = poses > 0
        detail = {"repaired": report is not None, "ee_pose_messages": poses}
    except (BagError, Exception) as err:  # noqa: BLE001 - any failure to read it back is a lost episode
        readable, detail = False, {"error": f"{type(err).__name__}: {err}"}
    c.home()
    return {"survived": readable and c.alive() and moved > 0.02, **detail}


JAM_S = 6.0  # how long the gripper stays jammed


def fault_gripper_stuck(c: Campaign) -> dict:
    def width() -> float:
        return gripper_width_from_joint_state(c.client.data.last_joint_state)

    def send_width(target: float, seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            c.client.publish_chunk(c.hold_chunk(width=target))
            time.sleep(0.2)

    c.client.wait_for(lambda: (send_width(0.08, 0.2), abs(width() - 0.08) < 0.004)[1], 30.0, "the fingers to open")
    stamps = c.client.pose_stamps if hasattr(c.client, "pose_stamps") else c.client.record_pose_stamps()
    c.sim.jam_gripper(True)
    t0, w0, start = time.time(), width(), c.here()
    send_width(0.02, 2.0)  # close on nothing: 60 mm in 1.2 s, were the fingers free
    change = abs(width() - w0)
    target = start + [0.0, 0.03, 0.0]
    c.probe.approach(c.client, target, speed=0.03, settle=0.5)  # the arm goes on meanwhile
    try:  # a sim below real time gets there later (held on the target by the last chunk, then the watchdog)
        c.client.wait_for(lambda: np.linalg.norm(c.here() - target) < 0.005, 3.0, "the arm at its target")
    except TimeoutError:
        pass
    reached = float(np.linalg.norm(c.here() - target))
    # past FrankyConfig.gripper_command_timeout_s (5 s): franka_node warns that the command has not finished
    time.sleep(max(0.0, t0 + JAM_S - time.time()))
    t1 = time.time()
    s = np.sort([t for t in list(stamps) if t0 <= t <= t1])
    gap = float(np.max(np.diff(np.concatenate([[t0], s, [t1]]))))
    c.sim.jam_gripper(False)
    send_width(0.05, 0.2)  # a new width after the jam cleared
    try:
        c.client.wait_for(
            lambda: (send_width(0.05, 0.2), abs(width() - 0.05) < 0.004)[1], 30.0, "the fingers to follow again"
        )
        followed = True
    except TimeoutError:
        followed = False
    send_width(0.08, 0.2)
    faulted = c.client.diag_value("franka_node", "faulted") == "True"
    return {
        "survived": change < 0.004 and reached < 0.005 and gap < JAM_S / 2 and followed and c.alive() and not faulted,
        "jammed_width_change_mm": round(change * 1000, 1),
        "arm_error_mm": round(reached * 1000, 2),
        "largest_state_gap_s": round(gap, 3),
        "fingers_followed_after": followed,
        "pending_command_warned": "has not finished" in franka_log(c),
    }
