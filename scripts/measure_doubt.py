"""Roll a policy out in-process with K samples per observation and score each doubt candidate's AUROC
for failure (docs/results/doubt.md). Resumable: one JSON line per episode in --log; seeds already there are
skipped. ``--report`` only summarises the log; ``--gate FILE`` adds what the doubt gate calibrated in FILE
would have flagged on the logged roll-outs.

    python scripts/measure_doubt.py --policy checkpoints/demos/equidiff_10 --episodes 40 --log doubt.jsonl
"""

from __future__ import annotations

import argparse
import gzip
import json
import logging
import sys
from pathlib import Path

from equidiff_core.benches.doubt import auroc, auroc_ci95, episode_scores, roll_out_doubt
from equidiff_core.benches.training_runs import run_policy
from equidiff_core.policy.inference import load_inference_policy
from equidiff_core.twin.config import load_twin_job_configs
from equidiff_core.twin.evaluate import in_range_yaw_seeds


def read_log(log_path: Path) -> list[dict]:
    """The logged episodes (a .gz log, as kept in docs/results, is read as is)."""
    text = gzip.decompress(log_path.read_bytes()).decode() if log_path.suffix == ".gz" else log_path.read_text()
    return [json.loads(line) for line in text.splitlines() if line.strip()]


def report(log_path: Path, windows_s=(None, 10.0, 5.0)) -> dict:
    """AUROC for failure of each candidate, per episode score (max, q90, mean of its chunks) and window (the
    chunks observed in the first W s only: a failure runs to the time limit, so over the whole episode it has
    more chunks to reach a high max than a success that ends early)."""
    episodes = read_log(log_path)
    out = {"episodes": len(episodes), "failures": sum(not e["success"] for e in episodes), "auroc": {}}
    for window in windows_s:
        for label, q in (("max", 1.0), ("q90", 0.9), ("mean", None)):
            scored = []
            for e in episodes:
                chunks = [
                    {k: v for k, v in c.items() if k != "stamp_ns"}
                    for c in e["chunks"]
                    if window is None or c["stamp_ns"] < window * 1e9
                ]
                if q is None:
                    names = {n for c in chunks for n in c}
                    vals = {n: [c[n] for c in chunks if n in c and c[n] == c[n]] for n in names}
                    scored.append((e["success"], {n: sum(v) / len(v) for n, v in vals.items() if v}))
                else:
                    scored.append((e["success"], episode_scores(chunks, q)))
            names = sorted({n for _, s in scored for n in s})
            key = label if window is None else f"{label}_first_{window:g}s"
            groups = {
                n: (
                    [s[n] for ok, s in scored if not ok and n in s and s[n] == s[n]],
                    [s[n] for ok, s in scored if ok and n in s and s[n] == s[n]],
                )
                for n in names
            }
            out["auroc"][key] = {n: auroc(*g) for n, g in groups.items()}
            if label == "max":  # the score the docs compare by: its bootstrap interval
                out.setdefault("auroc_ci95", {})[key] = {n: auroc_ci95(*g) for n, g in groups.items()}
    return out


def gate_preview(log_path: Path, policy_file: Path, quantiles=(0.9, 0.95, 0.99, 1.0)) -> dict:
    """What the doubt gate would have done on the logged roll-outs, at each quantile of the calibration stored in
    ``policy_file`` (``equidiff check doubt --write``): the share of failures and of successes with a chunk above
    the threshold (the first alarm would have held the arm), and the median sim second of the failures' first."""
    calibration = load_inference_policy(policy_file).doubt_calibration
    if calibration is None:
        raise SystemExit(f"{policy_file} holds no doubt calibration (equidiff check doubt --write)")
    episodes = read_log(log_path)
    out = {"signal": calibration.signal, "calibration_frames": len(calibration.values_m), "quantiles": {}}
    for q in quantiles:
        threshold = calibration.threshold(q)

        def first_alarm_s(e, threshold=threshold):
            for c in e["chunks"]:
                value = c.get(calibration.signal if calibration.signal != "spread" else f"spread_{calibration.samples}")
                if value is not None and value > threshold:  # NaN: no alarm
                    return c["stamp_ns"] / 1e9
            return None

        fails = [first_alarm_s(e) for e in episodes if not e["success"]]
        oks = [first_alarm_s(e) for e in episodes if e["success"]]
        flagged = sorted(t for t in fails if t is not None)
        out["quantiles"][f"q{q:g}"] = {
            "threshold_m": round(threshold, 5),
            "failures_flagged": f"{len(flagged)} of {len(fails)}",
            "successes_flagged": f"{sum(t is not None for t in oks)} of {len(oks)}",
            "median_first_alarm_s_in_failures": flagged[len(flagged) // 2] if flagged else None,
        }
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--policy", type=Path, default=Path("checkpoints/demos/equidiff_10"))
    ap.add_argument("--episodes", type=int, default=40)
    ap.add_argument("--samples", type=int, default=8)
    ap.add_argument("--max-duration", type=float, default=30.0)
    ap.add_argument("--latency-ms", type=float, default=100.0)
    ap.add_argument("--train-yaw", type=float, nargs=2, default=(-15.0, 15.0))
    ap.add_argument("--log", type=Path, required=True)
    ap.add_argument("--cache", type=Path, default=Path("runs/doubt"))
    ap.add_argument("--report", action="store_true")
    ap.add_argument("--gate", type=Path, default=None, help="also preview the gate of this calibrated policy file")
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s", stream=sys.stderr)
    if not args.report:
        configs = load_twin_job_configs(None, None)
        seeds = in_range_yaw_seeds(configs.twin, tuple(args.train_yaw), args.episodes)
        done = set()
        if args.log.exists():
            done = {e["seed"] for e in read_log(args.log)}
        policy = load_inference_policy(run_policy(args.policy, args.cache / args.policy.name))

        def on_episode(record):
            with args.log.open("a") as f:
                f.write(json.dumps(record) + "\n")

        roll_out_doubt(
            policy,
            configs.twin,
            configs.lab,
            [s for s in seeds if s not in done],
            args.samples,
            args.max_duration,
            args.latency_ms / 1000,
            logging.info,
            on_episode,
        )
    print(json.dumps(report(args.log)))
    if args.gate is not None:
        print(json.dumps(gate_preview(args.log, args.gate)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
