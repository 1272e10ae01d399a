"""How unsure the policy is of a chunk: the doubt signals, shared by policy_node and the in-process roll-outs.

Two signals, both in metres of gripper position over a chunk's steps (docs/doubt.md says which is
the default and why; docs/results/doubt.md has the measurement):

- ``chunk_disagreement``: how far the new chunk strays from the part of the previous chunk that has
  not run yet (the previous prediction's steps from the new observation's stamp on). Free: it needs
  no extra inference. A policy that keeps changing its mind is one that does not know what to do.
- ``sample_spread``: the spread of K DDIM samples that share one encoder pass
  (``InferencePolicy.predict_samples``): where the demos agree the samples do too.

``DoubtTracker`` keeps what ``chunk_disagreement`` needs between chunks (the previous prediction,
its stamp) and returns a ``ChunkDoubt`` per chunk; policy_node and ``twin.direct_execution.DirectPolicy``
both use it, so the live and the in-process signal cannot drift apart.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .. import geometry

SIGNALS = ("disagreement", "spread")
DEFAULT_SIGNAL = "disagreement"
DEFAULT_SAMPLES = 1  # samples per observation: 1 draws no more than plain DDIM (no spread)


def _positions(actions: np.ndarray, name: str) -> np.ndarray:
    a = np.asarray(actions, dtype=np.float64)
    if a.ndim < 2 or a.shape[-1] != 10 or not np.isfinite(a).all():
        raise ValueError(f"{name} must be finite (..., steps, 10) actions, got shape {a.shape}")
    return a[..., geometry.POS]


def sample_spread(samples: np.ndarray) -> float:
    """(K, steps, 10) absolute actions sampled for one observation -> the mean over steps of the samples'
    RMS distance (m) from their mean position. 0 for identical samples; needs K >= 2."""
    p = _positions(samples, "samples")
    if p.ndim != 3 or p.shape[0] < 2:
        raise ValueError(f"samples must be (K >= 2, steps, 10), got {np.shape(samples)}")
    deviation = p - p.mean(axis=0, keepdims=True)
    return float(np.sqrt((deviation**2).sum(axis=-1).mean(axis=0)).mean())


def chunk_disagreement(previous: np.ndarray, previous_stamp_ns: int, actions: np.ndarray, stamp_ns: int, dt_ns: int):
    """The mean distance (m) between ``actions`` (steps, 10; step i at ``stamp_ns`` + i·dt) and ``previous``
    (stamped ``previous_stamp_ns``) at the same times, over the steps of ``actions`` that fall within the
    previous chunk: what of it had not run yet when this one was observed. Between two steps of
    ``previous`` its positions are interpolated (camera stamps need not fall on its dt grid). None when
    they do not overlap (the previous one is used up, or is newer)."""
    new, old = _positions(actions, "actions"), _positions(previous, "previous")
    if new.ndim != 2 or old.ndim != 2:
        raise ValueError(f"actions and previous must be (steps, 10), got {np.shape(actions)}, {np.shape(previous)}")
    if dt_ns <= 0:
        raise ValueError(f"dt_ns must be > 0, got {dt_ns}")
    offset = (int(stamp_ns) - int(previous_stamp_ns)) / int(dt_ns)  # the new chunk's step 0 in previous' steps
    if offset < 0:
        return None
    at = offset + np.arange(len(new))
    inside = at <= len(old) - 1 + 1e-9
    if not inside.any():
        return None
    at = np.minimum(at[inside], len(old) - 1)
    grid = np.arange(len(old))
    then = np.stack([np.interp(at, grid, old[:, axis]) for axis in range(3)], axis=-1)
    return float(np.linalg.norm(new[inside] - then, axis=-1).mean())


@dataclass(frozen=True)
class ChunkDoubt:
    """The doubt of one chunk: both signals (NaN where not computed: no overlap with the previous chunk,
    or a single sample) and the one that ``signal`` names as ``value``."""

    stamp_ns: int
    disagreement_m: float
    spread_m: float
    signal: str = DEFAULT_SIGNAL

    @property
    def value(self) -> float:
        return self.disagreement_m if self.signal == "disagreement" else self.spread_m

    def as_dict(self) -> dict:
        return {"stamp_ns": self.stamp_ns, "signal": self.signal, "value": self.value,
                "disagreement_m": self.disagreement_m, "spread_m": self.spread_m}  # fmt: skip


class DoubtTracker:
    """Per episode (``reset``), the doubt of each chunk in turn: ``update(stamp, samples)`` with the
    prediction's samples (K, steps, 10), the first one the chunk that runs."""

    def __init__(self, dt_ns: int, signal: str = DEFAULT_SIGNAL):
        if signal not in SIGNALS:
            raise ValueError(f"signal must be one of {SIGNALS}, got {signal!r}")
        self.dt_ns, self.signal = int(dt_ns), signal
        self.reset()

    def reset(self) -> None:
        self._previous: tuple[int, np.ndarray] | None = None

    def update(self, stamp_ns: int, samples: np.ndarray) -> ChunkDoubt:
        samples = np.asarray(samples)
        if samples.ndim == 2:
            samples = samples[None]
        disagreement = None
        if self._previous is not None:
            disagreement = chunk_disagreement(self._previous[1], self._previous[0], samples[0], stamp_ns, self.dt_ns)
        spread = sample_spread(samples) if len(samples) > 1 else None
        self._previous = (int(stamp_ns), samples[0].copy())
        nan = math.nan
        return ChunkDoubt(
            int(stamp_ns),
            nan if disagreement is None else disagreement,
            nan if spread is None else spread,
            self.signal,
        )


# --- the gate: a threshold calibrated on the policy's own demos ------------------------------

DEFAULT_GATE = False  # off until measured in the twin (docs/doubt.md)
DEFAULT_GATE_QUANTILE = 0.99
HELP_REASON = "asks for help"  # policy_node's /policy/state while its gate holds the arm: "paused asks for help: <why>"


@dataclass(frozen=True)
class DoubtCalibration:
    """The doubt signal on the policy's own training demos (``calibrate_doubt``), stored in the policy file
    (``policy.file.with_doubt_calibration``): every answered frame's value, so a gate can take any quantile."""

    signal: str
    samples: int
    values_m: tuple[float, ...]  # sorted; the frames where the signal has a value
    episodes: int

    def __post_init__(self):
        if self.signal not in SIGNALS:
            raise ValueError(f"doubt calibration signal must be one of {SIGNALS}, got {self.signal!r}")
        if self.samples < 1 or (self.signal == "spread" and self.samples < 2):
            raise ValueError(f"doubt calibration of {self.signal} with {self.samples} samples")
        values = np.asarray(self.values_m, dtype=np.float64)
        if values.ndim != 1 or not len(values) or not np.isfinite(values).all() or (values < 0).any():
            raise ValueError("doubt calibration values must be a non-empty list of finite values >= 0")

    def threshold(self, quantile: float) -> float:
        """The ``quantile`` (0 < q <= 1) of the signal over the demos' frames: above it, the policy is less
        sure than on all but 1 - q of its own training frames."""
        if not 0 < quantile <= 1:
            raise ValueError(f"quantile must be in (0, 1], got {quantile}")
        return float(np.quantile(self.values_m, quantile))

    def as_dict(self) -> dict:
        return {"signal": self.signal, "samples": self.samples, "episodes": self.episodes,
                "values_m": [round(v, 6) for v in self.values_m]}  # fmt: skip

    @classmethod
    def from_dict(cls, d: dict) -> DoubtCalibration:
        try:
            return cls(
                str(d["signal"]), int(d["samples"]), tuple(sorted(map(float, d["values_m"]))), int(d["episodes"])
            )
        except (KeyError, TypeError) as err:
            raise ValueError(f"malformed doubt calibration: {err!r}") from err


class DoubtGate:
    """Asks for help when a chunk's doubt exceeds the calibration's ``quantile``: ``alarm(doubt)`` is why, or ""."""

    def __init__(self, calibration: DoubtCalibration, quantile: float, signal: str, samples: int):
        if calibration.signal != signal:
            raise ValueError(
                f"the policy's doubt was calibrated on {calibration.signal!r}, not on the signal in use ({signal!r})"
            )
        if signal == "spread" and calibration.samples != samples:
            raise ValueError(f"the spread was calibrated with {calibration.samples} samples, not {samples}")
        self.calibration, self.quantile = calibration, float(quantile)
        self.threshold_m = calibration.threshold(quantile)

    def alarm(self, doubt: ChunkDoubt) -> str:
        if not doubt.value > self.threshold_m:  # NaN (nothing to compare yet) never fires
            return ""
        return (
            f"doubt {doubt.value * 1000:.1f} mm ({doubt.signal}) above {self.threshold_m * 1000:.1f} mm, "
            f"the q{self.quantile:g} of its demos"
        )


def calibrate_doubt(policy, episodes, signal: str = DEFAULT_SIGNAL, samples: int = DEFAULT_SAMPLES, log=None):
    """The doubt signal of ``policy`` (an ``InferencePolicy``) on its demos (``data.episode_arrays.EpisodeArrays``):
    in each episode, open loop, the frames policy_node would answer (every ``n_action_steps``-th from the
    first), with ``wire.chunk.SamplingSeeds``' noise for the episode's index. ``log``: a progress callback."""
    from ..wire.chunk import SamplingSeeds

    tracker = DoubtTracker(round(policy.dt * 1e9), signal)
    seeds, values, count = SamplingSeeds(), [], 0
    resolution = policy.workspace.resolution
    for index, episode in enumerate(episodes):
        tracker.reset()
        seeds.start_episode(index)
        for frame in range(0, len(episode), policy.n_action_steps):
            grid, ee = episode.grid(frame, resolution), np.asarray(episode.ee[frame], dtype=np.float64)
            drawn = policy.predict_samples(grid, ee, samples, seed=seeds.next())
            value = tracker.update(int(episode.stamps_ns[frame]), drawn).value
            if math.isfinite(value):
                values.append(value)
        count += 1
        if log is not None:
            log(f"doubt calibration: episode {index + 1} ({len(values)} frames so far)")
    if not values:
        raise ValueError("no demo frame gave a doubt value (episodes shorter than two answers?)")
    return DoubtCalibration(signal, samples, tuple(sorted(values)), count)
