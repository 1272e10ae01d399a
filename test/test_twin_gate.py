"""The twin supervisor's gate (``twin.gate.PolicyGate``): which policy chunks reach the robot, and when."""

import numpy as np
import pytest

from equidiff_core.twin.gate import PolicyGate

MS = 1_000_000


def test_the_gate_passes_only_this_episodes_chunks_each_at_its_stamp_plus_latency():
    gate = PolicyGate(latency_ns=100 * MS)
    assert not gate.offer("before", 0, 50 * MS)  # closed: the policy is warm, nothing reaches the robot
    gate.open(1000 * MS)
    assert not gate.offer("old observation", 990 * MS, 1100 * MS)  # answers one from before the episode
    assert not gate.offer("a", 1000 * MS, 1020 * MS)  # held until 1100 ms
    assert not gate.offer("b", 1050 * MS, 1060 * MS)  # held until 1150 ms
    assert gate.chunks_seen == 4
    assert gate.due(1099 * MS) == []
    assert gate.due(1100 * MS) == [(1000 * MS, "a")]
    assert gate.forwarded(1000 * MS, 1100 * MS)
    assert gate.offer("late", 1010 * MS, 1200 * MS)  # already past its time: forward at once
    assert gate.forwarded(1010 * MS, 1200 * MS)
    record = gate.close()  # "b" was still held: dropped with the episode
    assert gate.due(2000 * MS) == []
    assert not gate.forwarded(1050 * MS, 2000 * MS)  # a forward racing the close does not count
    assert record.arrivals == [1.1, 1.2]
    assert record.end_to_end_ms == [100.0, 190.0]


def test_the_gate_counts_skipped_observations_and_inference_only_during_its_episode():
    gate = PolicyGate()
    gate.skipped(0, "busy")
    gate.inference(80.0)
    gate.open(1000 * MS)
    gate.skipped(900 * MS, "busy")  # an observation from before the episode
    gate.skipped(1000 * MS, "executing")  # the policy's execution schedule, not a drop
    gate.skipped(1200 * MS, "stale_observation")
    gate.inference(120.0)
    record = gate.close()
    assert record.dropped == ["stale_observation"]
    assert record.inference_ms == [120.0]
    gate.open(3000 * MS)  # a new episode starts from an empty record
    assert gate.close().dropped == []


@pytest.mark.ros
def test_a_homing_that_times_out_says_what_franka_node_reported(ros_domain):
    """The twin's homing error names the gripper, how old the joint states are and franka_node's own
    counts (chunks accepted and refused, gripper commands): enough to tell a stale state from a
    refused chunk from a gripper that never moved."""
    from diagnostic_msgs.msg import DiagnosticArray

    from equidiff_core.geometry import make_pose
    from equidiff_core.wire.rosmsg import RclpyFactory, diagnostic_array
    from equidiff_core.wire.topics import TOPIC_DIAGNOSTICS
    from equidiff_ros.common import RELIABLE_QOS
    from equidiff_ros.twin.supervisor import Supervisor, SupervisorError

    sup = Supervisor()
    try:
        pub = sup.node.create_publisher(DiagnosticArray, TOPIC_DIAGNOSTICS, RELIABLE_QOS)
        counts = {"state": "holding", "accepted_chunks": 7, "rejected_chunks": 2, "gripper_commands": 0}
        msg = diagnostic_array(RclpyFactory(), 0, "franka_node", "sim", 1, "holding: chunk refused", counts)
        sup.wait_for(lambda: pub.publish(msg) or sup.franka_diagnostics, 10.0, "the diagnostics")
        with sup.lock:
            sup.ee_pose, sup.width = make_pose(np.diag([1.0, -1.0, -1.0]), [0.45, 0.0, 0.3]), 0.04
        with pytest.raises(SupervisorError) as raised:
            sup.move_to(make_pose(np.diag([1.0, -1.0, -1.0]), [0.45, 0.0, 0.3]), 0.08, timeout_s=0.3)
    finally:
        sup.close()
    text = str(raised.value)
    assert "gripper 40 mm for 80 mm" in text and "joint states: none yet" in text  # ee_pose set by hand, no state
    assert "'holding: chunk refused' (state holding, accepted_chunks 7, rejected_chunks 2, gripper_commands 0)" in text
