"""The twin supervisor's gate (``twin.gate.PolicyGate``): which policy chunks reach the robot, and when."""

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
