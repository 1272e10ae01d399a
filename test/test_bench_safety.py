"""`equidiff bench safety` (issues 16 and 27): the fault campaign against the twin's franky-sim
through franka_node, on the faults issue 27 changed (the safety box at the speed limit, a robot
stop through the libfranka protocol, a killed franka_node that must hold when restarted);
`equidiff bench safety` runs all fourteen (docs/control.md), test_franka_stops.py the stops in
detail, test_control.py and test_franka_sim.py the rejected chunks."""

from __future__ import annotations

import pytest

pytest.importorskip("franky")
pytest.importorskip("franky_sim")
pytest.importorskip("rclpy")

from equidiff_ros.commands.bench_safety import run_campaign

pytestmark = [pytest.mark.sim, pytest.mark.ros, pytest.mark.slow]

FAULTS = ["out_of_box", "user_stop", "franka_node_killed"]


def test_fault_campaign_survives_every_fault_without_resuming_on_its_own(ros_domain, tmp_path):
    r = run_campaign(FAULTS, tmp_path)
    assert r["faults_tried"] == len(FAULTS), r
    assert r["faults_survived"] == r["faults_tried"], r["faults"]
    assert r["auto_resumes"] == 0, r
    assert r["episodes_lost"] == 0 and r["episodes_recorded"] == 1, r
    assert r["max_excursion_mm"] == 0.0, r  # the measured TCP never left the safety box
    assert r["faults"]["out_of_box"]["box_margin_mm"] > 0  # control.yaml's measured margin was in force
    assert all(a["speed_limited"] for a in r["faults"]["out_of_box"]["approaches"].values()), r
    assert r["franka_node_exit_code"] == 0, r
    assert r["start_hold"].startswith("franka_node started")  # it held at start until the bench acknowledged
    # the restarted franka_node found the killed one's unclean exit and held until acknowledged
    assert "uncleanly" in r["faults"]["franka_node_killed"]["awaiting_ack"]
    assert "still pressed" in r["faults"]["user_stop"]["reason"] and r["faults"]["user_stop"]["same_process"]
