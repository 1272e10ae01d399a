"""Closed-loop roll-outs of the benches (``twin.evaluate.evaluate_policy``), summarised, and kept on disk so that
a bench finished in parts does not roll a policy out twice."""

from __future__ import annotations

import dataclasses
import json
import statistics
from pathlib import Path

from ..output_files import staged_output
from ..twin.evaluate import EvalEpisode


def summarize(episodes: list[EvalEpisode]) -> dict:
    """Success and how far failures got: the fractions that reached the block and lifted it, the median
    closest approach of the TCP to the block."""
    if not episodes:
        return {"episodes": 0, "success": None, "reached": None, "lifted": None, "median_closest_to_block_m": None}
    n = len(episodes)
    return {
        "episodes": n,
        "success": round(sum(e.success for e in episodes) / n, 3),
        "reached": round(sum(e.reached for e in episodes) / n, 3),
        "lifted": round(sum(e.lifted for e in episodes) / n, 3),
        "median_closest_to_block_m": round(statistics.median(e.closest_to_block_m for e in episodes), 3),
    }


def save_rollouts(path: Path, episodes: list[EvalEpisode], settings: dict) -> None:
    """``episodes`` and the ``settings`` they were rolled out with (seeds, duration, latency, policy file)."""
    payload = {"settings": settings, "episodes": [dataclasses.asdict(e) for e in episodes]}
    with staged_output(path, force=True) as staged:  # rewritten as episodes come in, never half-written
        staged.path.write_text(json.dumps(payload, indent=1))


def load_rollouts(path: Path, settings: dict) -> list[EvalEpisode] | None:
    """The episodes saved at ``path`` if they were rolled out with exactly ``settings``; else None."""
    try:
        payload = json.loads(path.read_text())
        if payload["settings"] != json.loads(json.dumps(settings)):
            return None
        return [EvalEpisode(**e) for e in payload["episodes"]]
    except (OSError, ValueError, KeyError, TypeError):
        return None
