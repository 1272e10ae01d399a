"""Numbers that say whether execution is smooth and safe (``equidiff bench control`` and the sim tests).

All take time stamps in seconds and positions (N, 3) in metres and return plain floats/ints.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np


def resample(times: np.ndarray, positions: np.ndarray, hz: float = 100.0) -> tuple[np.ndarray, np.ndarray]:
    """Linear resampling onto a uniform grid (state messages arrive with jitter)."""
    times = np.asarray(times, dtype=np.float64)
    order = np.argsort(times)
    times, positions = times[order], np.asarray(positions, dtype=np.float64)[order]
    keep = np.concatenate([[True], np.diff(times) > 0])
    times, positions = times[keep], positions[keep]
    if len(times) < 2:
        raise ValueError("need at least two samples")
    grid = np.arange(times[0], times[-1], 1.0 / hz)
    return grid, np.stack([np.interp(grid, times, positions[:, i]) for i in range(positions.shape[1])], 1)


def tracking_rms(times: np.ndarray, positions: np.ndarray, reference: Callable[[float], np.ndarray]) -> float:
    """RMS distance (m) between measured positions and the reference at the same times."""
    ref = np.stack([reference(float(t)) for t in times])
    return float(np.sqrt(np.mean(np.sum((np.asarray(positions) - ref) ** 2, axis=1))))


def tracking_lag(
    times: np.ndarray,
    positions: np.ndarray,
    reference: Callable[[float], np.ndarray],
    max_lag_s: float = 0.3,
    step_s: float = 0.005,
) -> tuple[float, float]:
    """(lag s, RMS m at that lag): the time shift of the reference that fits the positions best.

    Splits a tracking error into "late" (a pure delay: controller lag, stale state stamps) and
    "off the path" (the RMS left after the shift)."""
    best = (0.0, tracking_rms(times, positions, reference))
    for lag in np.arange(step_s, max_lag_s + 1e-9, step_s):
        rms = tracking_rms(times, positions, lambda t, lag=lag: reference(t - lag))
        if rms < best[1]:
            best = (float(lag), rms)
    return best


def velocity_reversals(
    times: np.ndarray,
    positions: np.ndarray,
    tangent: Callable[[float], np.ndarray],
    threshold_m_s: float = 0.005,
    min_duration_s: float = 0.03,
    hz: float = 100.0,
) -> int:
    """How often the motion runs backwards along the path (stop-and-go or overshoot at chunk switches).

    Velocity is projected on the reference's unit tangent; a reversal is a stretch of at least
    ``min_duration_s`` where that progress speed is below ``-threshold_m_s``.
    """
    grid, pos = resample(times, positions, hz)
    vel = np.gradient(pos, grid, axis=0)
    # A 50 ms moving average: state messages carry ~0.1 mm quantisation and jitter.
    k = max(1, int(0.05 * hz))
    vel = np.stack([np.convolve(vel[:, i], np.ones(k) / k, mode="same") for i in range(3)], 1)
    tang = np.stack([tangent(float(t)) for t in grid])
    tang /= np.maximum(np.linalg.norm(tang, axis=1, keepdims=True), 1e-12)
    backwards = np.sum(vel * tang, axis=1) < -threshold_m_s
    count, run = 0, 0
    need = max(1, round(min_duration_s * hz))
    for b in backwards:
        run = run + 1 if b else 0
        if run == need:
            count += 1
    return count


def max_outside_box(positions: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> float:
    """Largest distance (m) of any position outside the axis-aligned box (0 if all inside)."""
    positions = np.asarray(positions, dtype=np.float64)
    below = np.maximum(np.asarray(lower) - positions, 0.0)
    above = np.maximum(positions - np.asarray(upper), 0.0)
    return float(np.max(np.linalg.norm(below + above, axis=1))) if len(positions) else 0.0


def settle_time(times: np.ndarray, positions: np.ndarray, tol_m: float = 2e-4) -> float | None:
    """The earliest time from which every later position stays within ``tol_m`` of the last one."""
    positions = np.asarray(positions, dtype=np.float64)
    if len(positions) < 2:
        return None
    away = np.linalg.norm(positions - positions[-1], axis=1) > tol_m
    if not away.any():
        return float(times[0])
    last_away = int(np.flatnonzero(away)[-1])
    return float(times[last_away + 1]) if last_away + 1 < len(times) else None


def max_drift(positions: np.ndarray, anchor: np.ndarray) -> float:
    """Largest distance (m) of the positions from ``anchor``."""
    return float(np.max(np.linalg.norm(np.asarray(positions) - np.asarray(anchor), axis=1)))


def percentiles_ms(values_s, qs=(50, 95)) -> list[float | None]:
    values = np.asarray(list(values_s), dtype=np.float64)
    if values.size == 0:
        return [None for _ in qs]
    return [round(float(np.percentile(values, q)) * 1000, 2) for q in qs]


# The commanded TCP "stands still" below these speeds. A plan that has run out holds its last
# pose exactly (speed 0); a policy moving through its own plan commands millimetres per 0.2 s step.
STILL_SPEED_M_S = 0.001
STILL_ANGULAR_SPEED_RAD_S = 0.005


def standstill_at_switches(
    times: np.ndarray,
    positions: np.ndarray,
    switch_times: np.ndarray,
    rotations: np.ndarray | None = None,
    holding: np.ndarray | None = None,
    still_speed_m_s: float = STILL_SPEED_M_S,
    still_angular_speed_rad_s: float = STILL_ANGULAR_SPEED_RAD_S,
) -> list[float]:
    """Seconds the TCP stands still at each chunk switch (docs/chunking.md, "Standstill at chunk boundaries").

    ``times`` (N,) s and ``positions`` (N, 3) m are the TCP samples (optionally ``rotations``
    (N, 3, 3)), ``switch_times`` the instants new chunks took over. Between consecutive samples
    the TCP stands still when its speed is below ``still_speed_m_s`` and (with rotations) its
    angular speed below ``still_angular_speed_rad_s``, or when the later sample is ``holding``
    (N,) (franka_node's watchdog hold: it moves the command once, to the measured pose, and holds). A switch's standstill is the unbroken still
    stretch around it: back from the switch over the still intervals before it (with the time
    from the last sample to the switch when that interval was still), and forward over the still
    intervals from the one the switch falls in (counted from the switch). 0 when the motion goes
    on through the switch; a plan that ran out before the next chunk came shows as the time the
    command sat at its last step. Switches outside the samples are left out."""
    t = np.asarray(times, dtype=np.float64)
    keep = np.concatenate([[True], np.diff(t) > 0])  # a repeated stamp adds nothing
    if not np.all(np.diff(t[keep]) > 0):
        raise ValueError("sample times must not go backwards")
    t, p = t[keep], np.asarray(positions, dtype=np.float64)[keep]
    if len(t) < 2:
        return []
    dt = np.diff(t)
    still = np.linalg.norm(np.diff(p, axis=0), axis=1) / dt < still_speed_m_s
    if rotations is not None:
        r = np.asarray(rotations, dtype=np.float64)[keep]
        relative = np.einsum("nji,njk->nik", r[:-1], r[1:])  # R_k^T R_{k+1}
        angle = np.arccos(np.clip((np.trace(relative, axis1=1, axis2=2) - 1) / 2, -1.0, 1.0))
        still &= angle / dt < still_angular_speed_rad_s
    if holding is not None:
        still |= np.asarray(holding, dtype=bool)[keep][1:]
    out = []
    for s in np.asarray(switch_times, dtype=np.float64):
        if not t[0] < s <= t[-1]:
            continue
        j = int(np.searchsorted(t, s, side="right")) - 1  # the last sample at or before the switch
        duration = 0.0
        k = j - 1  # intervals k = [t_k, t_k+1], back from the one ending at sample j
        if k >= 0 and still[k]:
            duration += s - t[j]
            while k >= 0 and still[k]:
                duration += dt[k]
                k -= 1
        k = j  # forward from the interval the switch falls in
        while k < len(still) and still[k]:
            duration += t[k + 1] - max(t[k], s)
            k += 1
        out.append(float(duration))
    return out


def standstill_summary(standstill_s: list[float], episode_s: float) -> dict:
    """``bench chunking``'s and ``bench control``'s fields for the standstills at chunk switches (s) over
    ``episode_s`` seconds of commanded motion: mean and p95 per switch, their sum and its share of the time."""
    values = np.asarray(standstill_s, dtype=np.float64)
    return {
        "standstill_mean_ms": round(float(values.mean()) * 1000, 1) if values.size else None,
        "standstill_p95_ms": round(float(np.percentile(values, 95)) * 1000, 1) if values.size else None,
        "standstill_total_s": round(float(values.sum()), 3),
        "standstill_fraction": round(float(values.sum()) / episode_s, 4) if episode_s > 0 else None,
    }
