"""`equidiff bench safety`: the fault campaign against the twin's franky-sim
through franka_node: a rejected chunk, a robot stop through the libfranka protocol and a killed
franka_node that must hold when restarted (the campaign's machinery end to end); `equidiff bench
safety` runs all fourteen (docs/control.md), test_franka_stops.py the stops in detail. Not
``out_of_box``: at the speed limit near the floor's corners franky-sim's torque-controlled arm
now and then oscillates until franka_node's joint-speed stop catches it (docs/control.md), which
makes it a bench figure, not a test; the margin and braking are test_control.py's, the box
through the node test_franka_sim.py's."""

from __future__ import annotations

import pytest

pytest.importorskip("franky")
pytest.importorskip("franky_sim")
pytest.importorskip("rclpy")

from equidiff_core.benches.fault_campaign import run_campaign
from equidiff_ros.benches.safety_probe import SafetyProbe

pytestmark = [pytest.mark.sim, pytest.mark.ros, pytest.mark.slow]

FAULTS = ["nan", "user_stop", "franka_node_killed"]


def test_fault_campaign_survives_every_fault_without_resuming_on_its_own(ros_domain, tmp_path):
    r = run_campaign(FAULTS, tmp_path, SafetyProbe())
    assert r["faults_tried"] == len(FAULTS), r
    assert r["faults_survived"] == r["faults_tried"], r["faults"]
    assert r["auto_resumes"] == 0, r
    assert r["episodes_lost"] == 0 and r["episodes_recorded"] == 1, r
    assert r["max_excursion_mm"] == 0.0, r  # the measured TCP never left the safety box
    assert r["franka_node_exit_code"] == 0, r
    assert r["start_hold"].startswith("franka_node started")  # it held at start until the bench acknowledged
    # the restarted franka_node found the killed one's unclean exit and held until acknowledged
    assert "uncleanly" in r["faults"]["franka_node_killed"]["awaiting_ack"]
    assert "still pressed" in r["faults"]["user_stop"]["reason"] and r["faults"]["user_stop"]["same_process"]
