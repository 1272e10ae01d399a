"""`equidiff bench safety` (issue 16 item 2): the fault campaign against franky-sim through
franka_node, every fault but the two that need a policy_node (its start-up alone costs more
than the rest; `equidiff bench safety` runs all ten, docs/control.md)."""

from __future__ import annotations

import pytest

pytest.importorskip("franky")
pytest.importorskip("franky_sim")
pytest.importorskip("rclpy")

from equidiff_ros.commands.bench_safety import FAULTS, POLICY_FAULTS, run_campaign

pytestmark = [pytest.mark.sim, pytest.mark.ros, pytest.mark.slow]


def test_fault_campaign_survives_every_fault_without_resuming_on_its_own(ros_domain, tmp_path):
    faults = [f for f in FAULTS if f not in POLICY_FAULTS]
    r = run_campaign(faults, tmp_path)
    assert r["faults_tried"] == len(faults), r
    assert r["faults_survived"] == r["faults_tried"], r["faults"]
    assert r["auto_resumes"] == 0, r
    assert r["episodes_lost"] == 0 and r["episodes_recorded"] == 2, r
    assert r["max_excursion_mm"] <= r["box_tol_mm"], r  # the floor margin: the hand never touched the table
    assert r["franka_node_exit_code"] == 0, r
    # the restarted franka_node found the killed one's unclean exit and held until acknowledged
    assert "uncleanly" in r["faults"]["franka_node_killed"]["awaiting_ack"]
