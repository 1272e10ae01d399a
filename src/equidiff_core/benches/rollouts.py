"""Closed-loop roll-outs of the benches (``twin.evaluate.evaluate_policy``), summarised, and kept on disk so that
a bench finished in parts does not roll a policy out twice."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import statistics
from collections.abc import Callable
from pathlib import Path

from ..policy.file import open_policy_file, weights_sha256
from ..runtime.output_files import staged_output
from ..twin.evaluate import EvalEpisode
from .stats import success_rate


def summarize(episodes: list[EvalEpisode]) -> dict:
    """Success (with n and its Wilson 95 % interval) and how far failures got: the fractions that reached the
    block and lifted it, the median closest approach of the TCP to the block."""
    if not episodes:
        return {
            "episodes": 0,
            "success": None,
            "successes": 0,
            "success_ci95": None,
            "reached": None,
            "lifted": None,
            "median_closest_to_block_m": None,
        }
    n = len(episodes)
    rate = success_rate([e.success for e in episodes])
    return {
        "episodes": n,
        "success": rate["rate"],
        "successes": rate["successes"],
        "success_ci95": rate["ci95"],
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


def policy_digest(path: Path) -> str:
    """What the roll-outs of a policy file depend on, its configuration and its weights' sha256, hashed: roll-outs
    saved for one policy are not reused for another, and are for the same policy re-exported or re-written (the
    file's bytes change, its weights do not)."""
    policy = open_policy_file(path)
    weights = policy.weights_sha256 or weights_sha256(policy.state)
    config = json.dumps(policy.config, sort_keys=True)
    return hashlib.sha256(f"{config}\n{weights}".encode()).hexdigest()[:16]


def cached_rollouts(
    cache: Path, settings: dict, roll_out: Callable[[], list[EvalEpisode]], log: Callable[[str], None]
) -> list[EvalEpisode]:
    """The roll-outs saved in ``cache`` for exactly ``settings``, else ``roll_out()``'s, saved there: a bench
    finished in parts, or re-run to report its figures anew, rolls no scene out twice."""
    done = load_rollouts(cache, settings)
    if done is not None:
        log(f"{len(done)} roll-outs reused from {cache}")
        return done
    done = roll_out()
    cache.parent.mkdir(parents=True, exist_ok=True)
    save_rollouts(cache, done, settings)
    return done


def resumable_rollouts(
    cache: Path,
    settings: dict,
    roll_one: Callable[[int], EvalEpisode],
    log: Callable[[str], None],
) -> list[EvalEpisode]:
    """``cached_rollouts`` scene by scene: the episodes saved in ``cache`` for exactly ``settings`` (the same
    file layout, so a complete file from ``cached_rollouts`` is reused as it is) and ``roll_one(seed)`` for each
    seed of ``settings["seeds"]`` not yet there, the file rewritten after each: an interrupted bench loses at
    most one scene."""
    seeds = list(settings["seeds"])
    saved = {e.seed: e for e in load_rollouts(cache, settings) or [] if e.seed in seeds}
    if saved:
        log(f"{len(saved)} of {len(seeds)} roll-outs reused from {cache}")
    cache.parent.mkdir(parents=True, exist_ok=True)
    for seed in seeds:
        if seed not in saved:
            saved[seed] = roll_one(seed)
            save_rollouts(cache, [saved[s] for s in seeds if s in saved], settings)
    return [saved[s] for s in seeds]
