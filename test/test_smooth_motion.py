"""Smooth motion by default: the online latency estimate that sizes policy_node's
chunks, and the standstill-at-chunk-boundaries metric of ``bench chunking`` and ``bench control``."""

from __future__ import annotations

import math

import numpy as np
import pytest

from equidiff_core.control.metrics import standstill_at_switches, standstill_summary
from equidiff_core.wire.chunk import (
    DEFAULT_TRANSPORT_S,
    LatencyEstimate,
    bridging_execute_steps,
    max_bridged_latency_s,
    steps_to_publish,
)

DT = 0.2
AVAILABLE = 16  # horizon 16, one observation step


def test_latency_estimate_fixed_off_and_bad_settings():
    assert LatencyEstimate(0.1).value_s == 0.1 and LatencyEstimate(0.1).source == "fixed"
    assert LatencyEstimate(0).value_s == 0.0
    off = LatencyEstimate(-1)
    assert off.off and off.value_s is None and off.source == "off"
    fixed = LatencyEstimate(0.3)
    fixed.add(2.0)  # a fixed L ignores what is measured
    assert fixed.value_s == 0.3
    for bad in ("fast", -0.5, 10, True, None, float("nan")):
        with pytest.raises(ValueError, match="latency_s must be"):
            LatencyEstimate(bad)
    with pytest.raises(ValueError, match="transport allowance"):
        LatencyEstimate("auto", transport_s=-0.1)


def test_latency_auto_converges_to_a_high_percentile_of_the_recent_measurements():
    est = LatencyEstimate("auto", initial_s=1.4)
    assert est.source == "auto (initial)" and est.value_s == 1.4
    for value in (0.3, 0.3, 0.3, 0.5):  # few measurements: the largest
        est.add(value)
    assert est.value_s == pytest.approx(0.5 + DEFAULT_TRANSPORT_S)
    rng = np.random.default_rng(0)
    for value in 0.30 + 0.02 * rng.standard_normal(200):
        est.add(value)
    recent = list(est.measured)
    assert len(recent) == LatencyEstimate.WINDOW and est.source == "auto"
    assert est.value_s == pytest.approx(sorted(recent)[18] + DEFAULT_TRANSPORT_S)  # p95 of 20: the 19th
    assert 0.30 + DEFAULT_TRANSPORT_S < est.value_s < 0.30 + 0.06 + DEFAULT_TRANSPORT_S
    est.add(0.9)  # one slow cycle in the window is an outlier...
    assert est.value_s < 0.4
    est.add(0.9)  # ...two are the p95: the estimate follows at once...
    assert est.value_s == pytest.approx(0.9 + DEFAULT_TRANSPORT_S)
    for _ in range(LatencyEstimate.WINDOW):  # ...and forgets them once the window has passed
        est.add(0.3)
    assert est.value_s == pytest.approx(0.3 + DEFAULT_TRANSPORT_S)
    est.add(float("nan"))  # not a measurement
    assert est.value_s == pytest.approx(0.3 + DEFAULT_TRANSPORT_S)


def plan_gaps(latencies_s, execute_steps: int, latency_setting="auto") -> list[float]:
    """Seconds each chunk boundary would stand still when policy_node sizes its chunks from
    ``LatencyEstimate`` (as it does: this chunk's own latency counts before it is sized): the
    observation answered every k periods (``execute_steps``; 0: policy_node's default, 8 or fewer
    when L needs it), its chunk arriving ``latency`` later, and the previous chunk's last step at
    its stamp + (steps - 1) dt."""
    est = LatencyEstimate(latency_setting)
    gaps, previous_end, stamp, k = [], None, 0.0, execute_steps or 8
    for latency in latencies_s:
        arrival = stamp + latency
        if previous_end is not None:
            gaps.append(max(0.0, arrival - previous_end))
        est.add(latency)
        steps = 8 if est.off else steps_to_publish(k, est.value_s, DT, AVAILABLE)
        previous_end = stamp + (steps - 1) * DT
        if not execute_steps and not est.off:  # the next answer comes after k' periods, sized by L
            k = bridging_execute_steps(8, est.value_s, DT, AVAILABLE)
        stamp += k * DT
    return gaps


@pytest.mark.parametrize("execute_steps", [1, 4, 8, 0])
def test_chunks_sized_by_the_estimate_bridge_the_measured_latency(execute_steps):
    rng = np.random.default_rng(execute_steps)
    latencies = list(0.35 + 0.05 * rng.random(40))  # a jittery 350-400 ms
    assert max(plan_gaps(latencies, execute_steps)) == 0.0  # the arm never stands at a boundary
    # without the estimate (the former default: whole chunks of 8, latency off) it stands dt + L each time
    if execute_steps == 8:
        assert min(plan_gaps(latencies, 8, -1)) == pytest.approx(DT + 0.35, abs=1e-9 + 0.05)
    # a latency beyond what k's chunks can bridge: with k fixed the gap is the excess; the default
    # k (0) answers sooner and bridges it, up to (16 - 1 - 1) dt with k = 1
    k_max = max_bridged_latency_s(execute_steps or 1, DT, AVAILABLE)
    if execute_steps:
        assert plan_gaps([k_max + 0.3] * 5, execute_steps)[-1] == pytest.approx(0.3)
    else:
        assert plan_gaps([1.9] * 10, 0) == [0.0] * 9  # k = 5: 5 + 10 + 1 = 16 steps
        assert plan_gaps([k_max + 0.3] * 5, 0)[-1] == pytest.approx(0.3)


def test_the_default_execution_horizon_shortens_only_when_the_latency_needs_it():
    assert [bridging_execute_steps(8, L, DT, AVAILABLE) for L in (0.0, 0.1, 1.4, 1.41, 1.9, 2.8, 5.0)] == [
        8,
        8,
        8,
        7,
        5,
        1,
        1,
    ]


def test_max_bridged_latency_is_the_inverse_of_steps_to_publish():
    for k in (1, 4, 8):
        limit = max_bridged_latency_s(k, DT, AVAILABLE)
        assert steps_to_publish(k, limit, DT, AVAILABLE) == AVAILABLE
        assert k + math.ceil(round((limit + DT) / DT, 6)) + 1 > AVAILABLE


def stop_and_go(standstill_s: float, boundaries: int = 4, chunk_s: float = 1.6, hz: float = 200.0):
    """A commanded TCP moving at 0.05 m/s through chunks of ``chunk_s``, standing still for
    ``standstill_s`` before each next chunk takes over (0: smooth). Returns (times, positions,
    switch times)."""
    times, positions, switches = [], [], []
    t = x = 0.0
    period = 1.0 / hz
    for _ in range(boundaries + 1):
        end_move = t + chunk_s
        while t < end_move - 1e-9:
            times.append(t)
            positions.append([x, 0.0, 0.3])
            x += 0.05 * period
            t += period
        end_still = t + standstill_s
        while t < end_still - 1e-9:
            times.append(t)
            positions.append([x, 0.0, 0.3])
            t += period
        switches.append(t)
    return np.array(times), np.array(positions), np.array(switches[:-1])


def test_standstill_metric_stop_and_go_against_smooth():
    times, positions, switches = stop_and_go(0.3)
    stills = standstill_at_switches(times, positions, switches)
    assert stills == pytest.approx([0.3] * 4, abs=0.006)  # one 5 ms sample
    times, positions, switches = stop_and_go(0.0)
    assert standstill_at_switches(times, positions, switches) == [0.0] * 4
    summary = standstill_summary([0.3, 0.3, 0.0, 0.1], episode_s=8.0)
    assert summary == {
        "standstill_mean_ms": 175.0,
        "standstill_p95_ms": 300.0,
        "standstill_total_s": 0.7,
        "standstill_fraction": 0.0875,
    }
    assert standstill_summary([], 0.0)["standstill_mean_ms"] is None


def test_standstill_counts_a_watchdog_hold_and_rotation_and_ignores_far_switches():
    times, positions, switches = stop_and_go(0.8, boundaries=1)
    holding = np.zeros(len(times), bool)
    i_hold = int(np.searchsorted(times, switches[0] - 0.3))  # the watchdog moves the command once, then holds
    i_switch = int(np.searchsorted(times, switches[0]))
    positions[i_hold:, 1] = 0.002
    holding[i_hold:i_switch] = True
    assert standstill_at_switches(times, positions, switches)[0] == pytest.approx(0.3, abs=0.006)
    assert standstill_at_switches(times, positions, switches, holding=holding)[0] == pytest.approx(0.8, abs=0.006)
    # turning in place is not standing still
    times, positions, switches = stop_and_go(0.3, boundaries=1)
    angles = np.where(np.arange(len(times)) * 0.005 >= switches[0] - 0.3, np.arange(len(times)) * 0.005 * 0.1, 0.0)
    rotations = np.stack([_rot_z(a) for a in angles])
    assert standstill_at_switches(times, positions, switches, rotations)[0] == pytest.approx(0.0, abs=0.006)
    assert standstill_at_switches(times, positions, [times[-1] + 1.0, times[0]]) == []


def _rot_z(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
