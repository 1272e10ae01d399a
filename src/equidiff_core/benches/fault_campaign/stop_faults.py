"""The robot stops franka_node must hold on until the operator acknowledges (``equidiff bench safety``):
a user stop, a collision reflex, a lost connection, a divergence at joint 7's limit, and franka_node
itself killed and started again. Each: held (the arm still, every chunk refused), not resumed on its
own, and following the chunks again after the acknowledgement.
"""

from __future__ import annotations

import contextlib
import signal
import threading
import time
from collections.abc import Callable

import numpy as np

from equidiff_core import geometry
from equidiff_core.benches.fault_campaign.campaign import STEP_NS, Campaign, Sender, start_franka
from equidiff_core.wire.chunk import PoseChunk
from equidiff_core.wire.rosmsg import arm_joint_positions


def held_until_acknowledged(
    c: Campaign,
    sender: Callable[[], None],
    inject: Callable[[], None],
    reason_starts: str,
    pressed: bool = False,
    after_fault_s: float = 0.0,
    resume: Callable[[], None] | None = None,
) -> dict:
    """The common course of a robot stop: ``inject`` it while ``sender`` publishes chunks (it goes
    on throughout), check that franka_node holds (the same process, /franka/status
    ``awaiting_ack`` with a reason starting ``reason_starts``, the arm still, every chunk
    refused); with ``pressed`` (the user stop) an acknowledgement is tried first and must be
    refused, then the stop is released; then acknowledge and check the arm follows again (the
    chunks of ``resume``, if given, from then on)."""
    pid, out = c.franka.pid, {}
    with Sender(sender) as policy:
        time.sleep(0.8)  # the arm follows the sender
        t_fault = time.time()
        inject()
        try:
            status = c.status.wait(lambda s: s.get("state") == "awaiting_ack", 15.0, "the held state", c.franka)
        except (TimeoutError, RuntimeError) as err:
            return {"survived": False, "error": str(err), "status": c.status.latest}
        out["held_after_s"] = round(time.time() - t_fault, 2)
        if pressed:  # franka_node names the pressed stop once it has polled the robot's mode (stops.STOPPED_POLL_HZ)
            with contextlib.suppress(TimeoutError, RuntimeError):
                status = c.status.wait(
                    lambda s: s.get("state") == "awaiting_ack" and "still pressed" in s.get("reason", ""),
                    5.0,
                    "the held state naming the pressed user stop",
                    c.franka,
                )
        out["reason"] = status["reason"][:120]
        time.sleep(max(0.0, t_fault + after_fault_s - time.time()))  # e.g. until a dropped link answers again
        time.sleep(0.5)  # the arm brakes
        c.client.wait_for(  # the 1 Hz diagnostics have caught up with the stop: a baseline for the count
            lambda: c.client.diag_value("franka_node", "state") == "awaiting_ack", 5.0, "diagnostics of the stop"
        )
        accepted, rejected, t_held = c.diag("accepted_chunks"), c.diag("ack_rejected"), time.time()
        time.sleep(2.0)
        refused = c.wait_diag("ack_rejected", rejected, timeout=3.0)
        if pressed:
            granted, message = c.probe.acknowledge()
            out["ack_while_pressed_refused"] = not granted and "still pressed" in message
            c.sim.inject("release")
            time.sleep(1.0)
        policy.publish = resume or sender  # refused until the acknowledgement anyway
        time.sleep(0.3)
        accepted_while_held = c.diag("accepted_chunks") > accepted
        t_ack = time.time()
        granted, message = c.probe.acknowledge()
        out["acknowledged"] = message[:120]
        # the arm from the stop until the acknowledgement, and the state read as it recovered (the
        # first after it: a lost connection has no state in between, so this shows its drift)
        c.wait_past(t_ack + 0.5)
        t, p = c.client.samples("poses", t_held, time.time())
        p = np.concatenate([p[t <= t_ack], p[t > t_ack][:1]]) if len(t) else p
        held = float(np.max(np.linalg.norm(p - p[0], axis=1))) if len(p) else float("nan")
        resumed_alone = not held < c.still_m or accepted_while_held
        c.auto_resumes += int(resumed_alone)
        accepted = c.diag("accepted_chunks")
        time.sleep(2.5)
        follows = c.wait_diag("accepted_chunks", accepted, timeout=3.0) and (
            c.moved_m(t_ack, time.time()) > 0.01 or resume is not None  # a turn of the hand moves the TCP little
        )
    c.note_excursion(t_fault)
    out.update(
        held_moved_mm=round(held * 1000, 2),
        refused_until_ack=refused,
        follows_after_ack=follows,
        same_process=c.franka.pid == pid and c.alive(),
    )
    out["survived"] = bool(
        out["reason"].startswith(reason_starts)
        and held < c.still_m
        and refused
        and not resumed_alone
        and granted
        and follows
        and out["same_process"]
        and out.get("ack_while_pressed_refused", True)
    )
    c.home()
    return out


def fault_user_stop(c: Campaign) -> dict:
    return held_until_acknowledged(
        c, lambda: c.follow_me(0.0), lambda: c.sim.inject("user_stop"), "user stop: ", pressed=True
    )


def fault_reflex(c: Campaign) -> dict:
    return held_until_acknowledged(c, lambda: c.follow_me(0.0), lambda: c.sim.inject("reflex"), "reflex: ")


def fault_connection_lost(c: Campaign) -> dict:
    return held_until_acknowledged(
        c,
        lambda: c.follow_me(0.0),
        lambda: c.sim.inject("drop", 1.5),
        "connection to the robot lost",
        after_fault_s=2.0,  # the robot answers again (to a new connection) before the operator acknowledges
    )


def fault_divergence(c: Campaign) -> dict:
    """The sender yaws the hand on and on (0.5 rad/s, the speed limit is 0.6) until joint 7 runs
    into its position limit: franka_node's divergence stop. Joint 7 turns against the yaw about
    the base's z while the hand points down; the sender heads for the nearer of its limits."""
    q7 = float(arm_joint_positions(c.client.data.last_joint_state)[6])
    lo, hi = c.joint_limits[0][6], c.joint_limits[1][6]
    yaw_sign = -1.0 if hi - q7 < q7 - lo else 1.0
    rate = 0.5

    def yawing():  # from the measured pose on, as a policy answering observations would
        now, here = time.time_ns(), c.status.ee_pose
        times = now + np.arange(8, dtype=np.int64) * STEP_NS
        poses = [
            geometry.make_pose(geometry.rotz(yaw_sign * rate * 0.2 * (i + 1)) @ here[:3, :3], here[:3, 3])
            for i in range(8)
        ]
        c.client.publish_chunk(PoseChunk(now, times, np.stack(poses), np.full(8, 0.08)))

    stopped = {}

    def inject():  # the yawing itself is the fault: wait for it to run into the limit
        c.status.wait(lambda s: s.get("state") == "awaiting_ack", 20.0, "the divergence stop", c.franka)
        stopped["q7"] = float(arm_joint_positions(c.client.data.last_joint_state)[6])

    def unyawing():  # after the acknowledgement: back, away from the limit (towards it would stop again)
        now, here = time.time_ns(), c.status.ee_pose
        times = now + np.arange(8, dtype=np.int64) * STEP_NS
        poses = [
            geometry.make_pose(geometry.rotz(-yaw_sign * 0.3 * 0.2 * (i + 1)) @ here[:3, :3], here[:3, 3])
            for i in range(8)
        ]
        c.client.publish_chunk(PoseChunk(now, times, np.stack(poses), np.full(8, 0.08)))

    result = held_until_acknowledged(c, yawing, inject, "divergence stop: joint 7", resume=unyawing)
    result["q7_start_rad"], result["q7_at_stop_rad"] = round(q7, 3), round(stopped.get("q7", float("nan")), 3)
    return result


def fault_franka_node_killed(c: Campaign) -> dict:
    stop = threading.Event()

    def policy():  # the policy goes on publishing whatever happens to franka_node
        while not stop.is_set():
            c.follow_me(0.2, direction=(0.0, -1.0, 0.0))

    sender = threading.Thread(target=policy, daemon=True)
    sender.start()
    try:
        time.sleep(1.0)  # mid-chunk: the arm is moving
        at_kill = c.here()
        c.franka.send_signal(signal.SIGKILL)
        c.franka.wait(timeout=10)
        t_killed = time.time()
        c.client.data.diagnostics.pop("franka_node", None)  # the dead node's
        restarted = start_franka(c)
        c.client.wait_for(
            lambda: c.client.data.poses and c.client.data.poses[-1][0] > t_killed + 0.5,
            90.0,
            "/franka/ee_pose again",
            c.franka,
        )
        status = c.status.wait(lambda s: s.get("state") == "awaiting_ack", 10.0, "the restarted node's hold", c.franka)
        at_restart = c.here()
        awaiting = str(status.get("reason", ""))
        accepted, t_held = c.diag("accepted_chunks"), time.time()
        time.sleep(2.0)  # the policy's chunks keep coming, starting where the arm is
        held = c.moved_m(t_held, time.time())
        c.wait_diag("ack_rejected", 0, timeout=3.0)
        refused = c.diag("ack_rejected") > 0
        if held >= c.still_m or c.diag("accepted_chunks") > accepted:
            c.auto_resumes += 1
        acked, _ = c.probe.acknowledge()
        t_ack = time.time()
        time.sleep(2.0)
        resumed = c.moved_m(t_ack, time.time()) > 0.01
    finally:
        stop.set()
        sender.join(timeout=5)
    c.note_excursion(c.t_start)
    drift = float(np.linalg.norm(at_restart - at_kill))
    c.home()
    return {
        "survived": restarted and "uncleanly" in awaiting and refused and held < c.still_m and acked and resumed,
        "drift_while_down_mm": round(drift * 1000, 1),
        "held_after_restart_mm": round(held * 1000, 2),
        "awaiting_ack": awaiting[:80],
        "refused_until_ack": refused,
        "resumed_after_ack": resumed,
    }
