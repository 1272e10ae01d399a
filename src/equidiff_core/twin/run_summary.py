"""What the main job measures and how it reports it (ROS-free, unit-testable)."""

from __future__ import annotations

import json
from dataclasses import dataclass, field

import numpy as np

from equidiff_core.benches.stats import success_rate


@dataclass
class EpisodeRecord:
    seed: int
    success: bool = False
    duration_s: float = 0.0  # first policy command -> success (or the time limit)
    chunks: int = 0  # policy chunks forwarded to the robot
    dropped_cycles: int = 0  # observations due an answer that got none (policy_node's /policy/skipped)
    bag: str = ""
    end_to_end_ms: list[float] = field(default_factory=list)  # capture stamp -> chunk at the robot
    inference_ms: list[float] = field(default_factory=list)
    note: str = ""
    stalled: str = ""  # the stage that did not deliver (simulated time); '' if none


def percentile(values: list[float], q: float) -> float | None:
    return None if not values else round(float(np.percentile(values, q)), 1)


@dataclass
class RunSummary:
    episodes: list[EpisodeRecord]
    sim_rate: float | None = None  # sim steps per wall second / 1000 (1.0 = real time)
    policy: str = ""
    rrd: str = ""
    clock: str = "sim"  # "sim" (simulated time, lockstep) or "realtime"
    latency_budget_ms: float | None = None  # simulated time: a chunk takes effect at its observation + this
    wall_s: float | None = None  # wall seconds of the whole job (start-up included)

    MIN_REALTIME_FACTOR = 0.9

    @property
    def representative(self) -> bool:
        """A real-time run measures the policy only if the sim kept (nearly) real time."""
        return self.clock == "sim" or (self.sim_rate is not None and self.sim_rate >= self.MIN_REALTIME_FACTOR)

    def as_dict(self) -> dict:
        eps = self.episodes
        n = len(eps)
        e2e = [v for e in eps for v in e.end_to_end_ms]
        inf = [v for e in eps for v in e.inference_ms]
        ok = [e for e in eps if e.success]
        return {
            "episodes": n,
            "success_rate": round(len(ok) / n, 3) if n else 0.0,
            "success_ci95": success_rate([e.success for e in eps])["ci95"],
            "mean_episode_s": round(float(np.mean([e.duration_s for e in eps])), 2) if n else None,
            "mean_success_episode_s": round(float(np.mean([e.duration_s for e in ok])), 2) if ok else None,
            "inference_p50_ms": percentile(inf, 50),
            "inference_p95_ms": percentile(inf, 95),
            "end_to_end_p50_ms": percentile(e2e, 50),
            "end_to_end_p95_ms": percentile(e2e, 95),
            "dropped_cycles": int(sum(e.dropped_cycles for e in eps)),
            "chunks": int(sum(e.chunks for e in eps)),
            "sim_realtime_factor": None if self.sim_rate is None else round(self.sim_rate, 2),
            "stalled_episodes": sum(bool(e.stalled) for e in eps),
            "clock": self.clock,
            "latency_budget_ms": self.latency_budget_ms,
            "wall_s": None if self.wall_s is None else round(self.wall_s, 1),
            "representative": self.representative,
            "policy": self.policy,
            "rrd": self.rrd,
        }

    def human(self) -> str:
        d = self.as_dict()
        lines = [
            "",
            "== twin run summary ==",
            f"policy:            {d['policy']}",
            f"episodes:          {d['episodes']}",
            f"success rate:      {d['success_rate'] * 100:.0f} % of {d['episodes']}"
            + (f" (95 % interval {d['success_ci95'][0]:.0%}-{d['success_ci95'][1]:.0%})" if d["success_ci95"] else ""),
            f"mean episode time: {d['mean_episode_s']} s (successful: {d['mean_success_episode_s']} s)",
            f"inference:         p50 {d['inference_p50_ms']} ms, p95 {d['inference_p95_ms']} ms",
            (
                f"end to end:        p50 {d['end_to_end_p50_ms']} ms, p95 {d['end_to_end_p95_ms']} ms "
                "(camera capture -> chunk at the robot)"
            ),
            f"dropped cycles:    {d['dropped_cycles']} (observations due an answer that got none; {d['chunks']} chunks)",
            "clock:             "
            + (f"simulated time, latency budget {d['latency_budget_ms']} ms" if d["clock"] == "sim" else "real time"),
            f"sim speed:         {d['sim_realtime_factor']} x real time; whole job {d['wall_s']} s of wall time",
            f"stalled episodes:  {d['stalled_episodes']}",
            f"rerun recording:   {d['rrd'] or '-'}",
        ]
        if not d["representative"]:
            lines.append(
                f"NOT REPRESENTATIVE: on real time the sim ran at {d['sim_realtime_factor']}x (< "
                f"{self.MIN_REALTIME_FACTOR}x): this machine, not the policy, set the timing; "
                f"run without --realtime"
            )
        for e in self.episodes:
            outcome = "stalled" if e.stalled else "success" if e.success else "failure"
            lines.append(
                f"  seed {e.seed:>6}: {outcome} in {e.duration_s:.1f} s, "
                f"{e.chunks} chunks, {e.dropped_cycles} dropped {e.note}{e.stalled}  {e.bag}"
            )
        return "\n".join(lines)

    def json_line(self) -> str:
        d = self.as_dict()
        keys = (
            "episodes",
            "success_rate",
            "success_ci95",
            "inference_p95_ms",
            "end_to_end_p95_ms",
            "dropped_cycles",
            "inference_p50_ms",
            "end_to_end_p50_ms",
            "mean_episode_s",
            "chunks",
            "sim_realtime_factor",
            "stalled_episodes",
            "clock",
            "latency_budget_ms",
            "wall_s",
            "representative",
        )
        return json.dumps({k: d[k] for k in keys})
