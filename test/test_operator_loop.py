"""The operator loop's logic, ROS-free: franka_node's state and its fallback,
the keys, the confirmations and the reset countdown, on a clock the test owns."""

from __future__ import annotations

import json

import pytest
from helpers_data import SyntheticEpisode, write_synthetic_episode

from equidiff_core.control.controller import ControllerStats
from equidiff_core.lab.node_view import (
    DIAGNOSTICS_STALE_S,
    NodeView,
    parse_franka_status,
    robot_status_from_diagnostics,
)
from equidiff_core.lab.operator_loop import KEY_ROWS, KEYS, SERVICES, LoopConfig, OperatorLoop, Request, ResetCountdown
from equidiff_core.wire import rosmsg, topics
from equidiff_core.wire.rosmsg import rosbags_factory

T0 = 1000.0  # the loop's clock (monotonic seconds)


def status(state: str, reason: str = "", last_fault: str = "", last_fault_ns: int = 0) -> str:
    return json.dumps({"state": state, "reason": reason, "last_fault": last_fault, "last_fault_ns": last_fault_ns})


def franka_diagnostics(message: str, faulted: bool = False, awaiting_ack: str = "", **stats) -> tuple[str, dict]:
    """franka_node's /diagnostics status as the client reads it: built by the node's own message code
    from its controller's real statistics, with the controller's state keys beside them as the node adds them."""
    values = {**ControllerStats(**stats).as_dict(), "faulted": faulted, "awaiting_ack": awaiting_ack}
    array = rosmsg.diagnostic_array(rosbags_factory(), 0, "franka_node", "dryrun", rosmsg.OK, message, values)
    (s,) = array.status
    return s.message, {kv.key: kv.value for kv in s.values}


def kinds(requests: list[Request]) -> list[str]:
    return [r.kind for r in requests]


def loop_with(policy="paused by the operator", recorder="idle", robot="holding", **config) -> OperatorLoop:
    loop = OperatorLoop(LoopConfig(**{"reset_s": 10.0, **config}))
    loop.observe("policy", policy, T0)
    loop.observe("recorder", recorder, T0)
    loop.observe("teleop_active", False, T0)
    loop.observe("franka_status", status(robot), T0)
    return loop


def answer(loop: OperatorLoop, requests: list[Request], now: float, ok: bool = True, message: str = "done"):
    """The worker's part: answer each request in order; the requests that follow."""
    follow = []
    for r in requests:
        follow += loop.done(r, ok, message, now)
    return follow


# --- franka_node's state ----------------------------------------------------------------------


def test_franka_status_is_read_and_bad_ones_say_what_is_wrong():
    s = parse_franka_status(status("awaiting_ack", "robot error: reflex", "robot error: reflex", 1_700_000_000 * 10**9))
    assert (s.state, s.reason, s.source) == ("awaiting_ack", "robot error: reflex", topics.TOPIC_FRANKA_STATUS)
    assert s.describe() == "awaiting ack: robot error: reflex"
    with pytest.raises(ValueError, match="not JSON"):
        parse_franka_status("holding")
    with pytest.raises(ValueError, match="'state' must be one of"):
        parse_franka_status(json.dumps({"state": "dancing"}))
    with pytest.raises(ValueError, match="last_fault_ns"):
        parse_franka_status(json.dumps({"state": "holding", "last_fault_ns": "yesterday"}))


def test_without_franka_status_the_diagnostics_stand_in():
    """What franka_node publishes today: `faulted`, `awaiting_ack` and its holding/executing message."""
    cases = [
        (franka_diagnostics("holding"), "holding", ""),
        (franka_diagnostics("executing", last_divergence="tracking error 0.12 m"), "moving", ""),
        (franka_diagnostics("holding until acknowledged", awaiting_ack="robot error: reflex"), "awaiting_ack", "robot error: reflex"),
        (franka_diagnostics("faulted: too many robot errors", faulted=True), "faulted", "faulted: too many robot errors"),
    ]  # fmt: skip
    for (message, values), state, reason in cases:
        s = robot_status_from_diagnostics(message, values)
        assert (s.state, s.reason, s.source) == (state, reason, topics.TOPIC_DIAGNOSTICS), message
    assert robot_status_from_diagnostics(*cases[1][0]).last_fault == "tracking error 0.12 m"


def test_the_view_prefers_the_status_topic_and_says_where_the_state_came_from():
    view = NodeView(franka_diagnostics=franka_diagnostics("executing"), franka_diagnostics_at=T0)
    robot, note = view.robot(T0 + 1)
    assert robot.state == "moving" and "(no status)" in note and topics.TOPIC_DIAGNOSTICS in note
    view.franka_status = status("homing")
    assert view.robot(T0 + 1) == (parse_franka_status(status("homing")), "")
    view.franka_status = "{broken"  # a bad message: said, and the diagnostics still stand in
    robot, note = view.robot(T0 + 1)
    assert robot.state == "moving" and "not JSON" in note
    view.franka_status = None  # franka_node gone: its diagnostics go stale, the state is unknown
    robot, note = view.robot(T0 + DIAGNOSTICS_STALE_S + 1)
    assert robot is None and "s old" in note


# --- keys -------------------------------------------------------------------------------------


def test_every_key_is_on_the_screen_and_every_request_names_a_real_service():
    assert sorted("".join(keys for _group, keys in KEY_ROWS)) == sorted(KEYS)
    services = {v for k, v in vars(topics).items() if k.startswith("SERVICE_")}
    assert {Request(kind).service for kind in SERVICES} <= services
    screen = OperatorLoop().screen_text(T0)
    for _action, text in KEYS.values():
        assert text in screen


def test_an_episode_is_kept_then_the_arm_homes_and_the_countdown_runs():
    loop = loop_with(policy="running")
    start = loop.press("s", T0)
    assert kinds(start) == ["start"]
    assert answer(loop, start, T0, message="/data/bags/pick_0003") == []
    loop.observe("recorder", "recording /data/bags/pick_0003", T0 + 0.1)
    assert "RECORDING" in loop.screen_text(T0 + 65) and "1:04" in loop.screen_text(T0 + 65)

    assert kinds(loop.press("t", T0 + 69)) == ["pause"] and loop.takeover  # the SpaceMouse takes over
    keep = loop.press("k", T0 + 70)
    assert kinds(keep) == ["pause", "success"]  # the policy stops acting before the episode ends
    follow = answer(loop, keep, T0 + 71)
    assert kinds(follow) == ["home"]
    assert not loop.takeover  # the next episode starts with the policy paused: no takeover to show
    loop.observe("recorder", "idle", T0 + 71)
    loop.observe("policy", "paused by the operator", T0 + 71)
    assert (loop.counts.success, loop.counts.failure) == (1, 0)
    assert "1 kept (1 success, 0 failure)" in loop.screen_text(T0 + 71)
    assert "reset the scene: 6 s" in loop.screen_text(T0 + 75)
    assert loop.tick(T0 + 80) == [] and loop.countdown.active
    assert loop.tick(T0 + 81.5) == [] and not loop.countdown.active  # no auto start: the loop is ready
    assert "reset done: s starts the next episode" in loop.messages[-1]


def test_auto_start_waits_for_the_arm_and_never_enables_the_policy():
    loop = loop_with(recorder="recording /data/bags/pick_0000", auto_start=True, reset_s=5.0)
    assert answer(loop, loop.press("f", T0), T0) == [Request("home")]  # policy paused already: no pause
    loop.observe("recorder", "idle", T0)
    loop.observe("franka_status", status("homing"), T0 + 1)
    assert loop.tick(T0 + 6) == [] and loop.waiting_for_arm
    assert "starts once the arm holds" in loop.screen_text(T0 + 6)
    loop.observe("franka_status", status("holding"), T0 + 9)
    assert kinds(loop.tick(T0 + 9)) == ["start"]
    assert not loop.countdown.active and loop.tick(T0 + 20) == []


def test_discard_asks_first_and_any_other_key_or_silence_says_no():
    loop = loop_with(recorder="recording /data/bags/pick_0001")
    assert loop.press("x", T0) == [] and "delete /data/bags/pick_0001?" in loop.screen_text(T0)
    assert loop.press("n", T0 + 1) == [] and "cancelled" in loop.messages[-1]
    assert loop.press("x", T0 + 2) == [] and loop.tick(T0 + 30) == []  # unanswered: it expires
    assert loop.confirming is None and loop.press("y", T0 + 31) == []  # a late y does nothing
    loop.press("x", T0 + 40)
    discard = loop.press("y", T0 + 41)
    assert kinds(discard) == ["discard"]
    assert kinds(answer(loop, discard, T0 + 41)) == ["home"]
    assert (loop.counts.discarded, loop.counts.success) == (1, 0) and loop.countdown.active


def test_no_start_while_the_arm_homes_holds_for_an_ack_or_is_faulted():
    for state, says in (("homing", "homing"), ("awaiting_ack", "acknowledged"), ("faulted", "could not recover")):
        loop = loop_with(robot=state)
        assert loop.press("s", T0) == [] and says in loop.messages[-1], state
    loop = loop_with(robot="awaiting_ack")
    assert loop.press("p", T0) == [] and "not enabled" in loop.messages[-1]
    assert kinds(loop.press("a", T0)) == ["ack"]
    loop = loop_with(robot="awaiting_ack", policy="running")
    assert kinds(loop.press("a", T0)) == ["pause", "ack"]  # after the ack the arm holds; p hands it back
    assert kinds(loop.press("h", T0)) == ["pause", "home"]


def test_policy_keys_and_the_spacemouse_takeover():
    loop = loop_with(policy="paused waiting for an enable (start_paused)")
    assert kinds(loop.press("p", T0)) == ["enable"]
    loop.observe("policy", "running", T0 + 1)
    assert kinds(loop.press("P", T0 + 2)) == ["pause"]  # caps lock on: the same key
    assert kinds(loop.press(" ", T0 + 3)) == ["pause"]  # space always pauses
    assert kinds(loop.press("t", T0 + 4)) == ["pause"] and loop.takeover
    assert "the SpaceMouse has the arm" in loop.screen_text(T0 + 4)
    loop.observe("teleop_active", True, T0 + 5)
    assert "SPACEMOUSE DRIVING" in loop.screen_text(T0 + 5)
    loop.observe("policy", "running", T0 + 6)  # handed back (p)
    assert not loop.takeover
    loop.observe("policy", None, T0 + 7)  # policy_node gone
    assert loop.press("p", T0 + 7) == [] and "no policy node" in loop.messages[-1]


def test_the_policy_asking_for_help_is_on_the_screen_with_why_and_the_keys_that_answer():
    loop = loop_with(policy="running")
    why = "doubt 41.0 mm (disagreement) above 23.5 mm, the q0.99 of its demos"
    loop.observe("policy", f"paused asks for help: {why}", T0 + 1)  # policy_node's gate fired
    screen = loop.screen_text(T0 + 1)
    assert "ASKS FOR HELP" in screen and why in screen and "p: let the policy go on" in screen
    assert why in loop.messages[-1] and "t hands the arm to the SpaceMouse" in loop.messages[-1]
    assert kinds(loop.press("t", T0 + 2)) == [] and loop.takeover  # already paused: the SpaceMouse just drives
    assert kinds(loop.press("p", T0 + 3)) == ["enable"]  # the policy goes on
    loop.observe("policy", "running", T0 + 4)
    assert "ASKS FOR HELP" not in loop.screen_text(T0 + 4) and not loop.takeover


def test_countdown_start_now_cancel_and_quit():
    loop = loop_with(recorder="recording /d/e_0000", auto_start=True)
    answer(loop, loop.press("k", T0), T0)
    loop.observe("recorder", "idle", T0)
    assert kinds(loop.press("s", T0 + 2)) == ["start"] and not loop.countdown.active  # ready early
    loop.countdown.start(T0 + 3)
    assert loop.press("c", T0 + 4) == [] and loop.tick(T0 + 60) == []  # cancelled: no auto start
    loop.observe("recorder", "recording /d/e_0001", T0 + 61)
    assert loop.press("q", T0 + 62) == [] and not loop.quit  # mid-episode: asks
    loop.press("y", T0 + 63)
    assert loop.quit


def test_a_refused_request_is_said_and_nothing_follows():
    loop = loop_with(recorder="recording /d/e_0000")
    keep = loop.press("k", T0)
    assert answer(loop, keep, T0, ok=False, message="/recorder/stop: not recording") == []
    assert loop.counts.success == 0 and not loop.countdown.active
    assert "FAILED to keep the episode as a success: /recorder/stop: not recording" in loop.messages[-1]


def test_countdown_on_its_own_clock():
    c = ResetCountdown(3.0)
    assert not c.active and not c.expired(T0) and c.remaining(T0) == 0.0
    c.start(T0)
    assert c.remaining(T0 + 1) == 2.0 and not c.expired(T0 + 2.9) and c.expired(T0 + 3)


def test_the_folder_count_is_the_kept_bags_without_the_one_being_recorded(tmp_path):
    out = tmp_path / "bags"
    for i in range(2):
        write_synthetic_episode(out / f"pick_{i:04d}", SyntheticEpisode(duration_s=0.4))
    loop = loop_with()
    start = loop.press("s", T0)
    write_synthetic_episode(out / "pick_0002", SyntheticEpisode(duration_s=0.4))  # its bag, not yet kept
    answer(loop, start, T0, message=str(out / "pick_0002"))  # the answer, before the recorder's status
    assert loop.output_dir == out  # learned from the recorder's path
    loop.tick(T0 + 6)
    assert loop.dataset_count == 2
    loop.observe("recorder", f"recording {out / 'pick_0002'}", T0 + 10)
    assert loop.dataset_count == 2 and f"in {out}: 2" in loop.screen_text(T0 + 10)
    answer(loop, loop.press("k", T0 + 11), T0 + 11)
    loop.observe("recorder", "idle", T0 + 11)
    assert loop.dataset_count == 3
    elsewhere = OperatorLoop(LoopConfig(output_dir=tmp_path / "on_the_recorder_machine"))
    elsewhere.tick(T0)
    assert elsewhere.dataset_count is None and ": ?" in elsewhere.screen_text(T0)


def test_equidiff_lab_alone_opens_the_screen_and_the_five_commands_stay():
    from equidiff_ros.cli import build_parser

    def parse(*argv):
        return build_parser(list(argv)).parse_args(list(argv))

    screen = parse("lab")
    assert (screen._module, screen.reset_s, screen.auto_start, screen.no_home) == ("lab_ui", 10.0, False, False)
    tuned = parse("lab", "--reset-s", "3", "--auto-start", "--output-dir", "bags")
    assert (tuned.reset_s, tuned.auto_start, str(tuned.output_dir)) == (3.0, True, "bags")
    assert (parse("lab", "record", "failure")._module, parse("lab", "record", "failure").action) == (
        "lab_record",
        "failure",
    )
    for sub in ("ack", "home", "status"):
        assert parse("lab", sub)._module == f"lab_{sub}"
    assert parse("lab", "policy", "pause")._module == "lab_policy"


def test_without_a_terminal_the_screen_says_to_use_the_commands():
    import os
    import subprocess
    import sys

    got = subprocess.run(
        [sys.executable, "-m", "equidiff_ros.cli", "lab"],
        stdin=subprocess.DEVNULL,
        capture_output=True,
        text=True,
        timeout=60,
        env=dict(os.environ, OMP_NUM_THREADS="1"),
    )
    assert got.returncode == 2 and "needs a terminal" in got.stderr and "lab record" in got.stderr


def test_a_diagnostics_entry_reads_its_numbers_and_quotes_its_counts():
    """The one reader of /diagnostics values: numbers only when finite, text and NaN as None."""
    values = {"inference_ms": 212.5, "state": "holding", "latency_ms": float("nan"), "accepted_chunks": 7}
    array = rosmsg.diagnostic_array(rosbags_factory(), 0, "policy_node", "cpu", rosmsg.OK, "running", values)
    (entry,) = rosmsg.diagnostic_entries(array)
    assert entry.number("inference_ms") == 212.5 and entry.number("accepted_chunks") == 7.0
    assert entry.number("state") is None and entry.number("latency_ms") is None and entry.number("absent") is None
    assert (
        entry.quote(("state", "accepted_chunks", "absent")) == "'running' (state holding, accepted_chunks 7, absent ?)"
    )
