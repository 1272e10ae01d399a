"""The main job (``equidiff twin run``): a policy evaluated end to end in the digital twin, every node a process.

The command's help text says what runs and what the summary holds.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

from equidiff_core.config import ConfigError
from equidiff_core.runtime.output_files import refuse_existing, write_output_text
from equidiff_core.twin.config import load_twin_job_configs
from equidiff_core.twin.processes import NodeProcessError
from equidiff_core.twin.run_summary import RunSummary
from equidiff_core.twin.shipped import resolve_policy
from equidiff_ros.twin.stack import TwinStack
from equidiff_ros.twin.supervisor import SupervisorError
from equidiff_ros.twin.world import run_policy_episode

# the run's summary files in OUT, beside its bags and logs
SUMMARY_JSON = "summary.json"
RUN_RRD = "twin_run.rrd"


def run_main_job(args) -> int:
    """``equidiff twin run`` for its parsed arguments: the episodes, the summary and its JSON line; the exit status.

    OUT keeps each episode's bag as it is written (numbered after those there); the run's summary files
    (summary.json, twin_run.rrd) land whole at the end, and an existing one is refused
    (``OutputExistsError``) before anything starts, unless ``args.force``."""
    out = args.out or Path("runs") / time.strftime("twin_run_%Y%m%d_%H%M%S")
    for summary_file in (SUMMARY_JSON, *(() if args.no_rrd else (RUN_RRD,))):
        refuse_existing(out / summary_file, args.force)  # now, not after the run
    try:
        configs = load_twin_job_configs(args.lab_config, args.twin_config)
    except ConfigError as err:
        print(f"equidiff twin run: {err}", file=sys.stderr)
        return 2
    lab_path, twin_path, lab, cfg = configs.lab_path, configs.twin_path, configs.lab, configs.twin
    episodes = 1 if args.smoke else args.episodes
    max_duration = args.max_duration or (8.0 if args.smoke else cfg.episode.max_duration_s)
    out.mkdir(parents=True, exist_ok=True)
    try:
        policy_path, policy_label = resolve_policy(
            out,
            lab.workspace,
            cfg,
            checkpoint=args.checkpoint,
            attach=args.attach,
            standin=args.standin or args.smoke,
            standin_preset="tiny" if args.smoke else "compact",
        )
    except FileNotFoundError as err:
        print(f"equidiff twin run: {err}", file=sys.stderr)
        return 2
    clock = args.clock
    realtime = clock == "realtime"
    print(
        f"[twin] policy: {policy_label}; {episodes} episode(s) of at most {max_duration:.0f} s; output {out}; "
        + ("real time" if realtime else f"simulated time, latency budget {args.latency_ms:.0f} ms")
    )
    records = []
    sim_rates = []
    wall_start = time.monotonic()
    try:
        with TwinStack(
            out,
            lab_path,
            twin_path,
            policy=str(policy_path),
            domain_id=args.domain,
            task="twin_eval",
            device=args.device,
            precision=args.precision,
            seed=args.seed,
            record_clouds=args.record_clouds,
            lenient=args.lenient or (args.smoke and realtime),
            attach=args.attach,
            realtime=realtime,
            latency_s=args.latency_ms / 1000.0,
            stall_timeout_s=args.stall_timeout,
            composed=args.composed,
        ) as stack:
            for i in range(episodes):
                missed = stack.sup.twin().get("missed_commands", 0)
                rec = run_policy_episode(stack, args.seed + i, max_duration)
                state = stack.sup.twin()
                sim_rates.append(state.get("steps_per_s", 0.0) / 1000.0)
                records.append(rec)
                outcome = "stalled" if rec.stalled else "success" if rec.success else "failure"
                print(
                    f"[twin] episode {i + 1}/{episodes} seed {rec.seed}: "
                    f"{outcome} in {rec.duration_s:.1f} s, {rec.chunks} chunks, "
                    f"{state.get('missed_commands', 0) - missed} ms of stale robot commands"
                    + (f" ({rec.stalled})" if rec.stalled else "")
                )
    except KeyboardInterrupt:
        print("[twin] interrupted: all nodes stopped", file=sys.stderr)
        if not records:
            return 130
    except (NodeProcessError, SupervisorError) as err:
        print(f"equidiff twin run: {err}", file=sys.stderr)
        return 1
    summary = RunSummary(
        records,
        sim_rate=sum(sim_rates) / len(sim_rates) if sim_rates else None,
        policy=policy_label,
        clock=clock,
        latency_budget_ms=None if realtime else args.latency_ms,
        wall_s=time.monotonic() - wall_start,
    )
    if not args.no_rrd and records:
        summary.rrd = write_rrd([r.bag for r in records if r.bag], out / RUN_RRD, lab, force=args.force)
    print(summary.human())
    write_output_text(out / SUMMARY_JSON, summary.json_line() + "\n", force=args.force)
    print(summary.json_line())
    return 0


def write_rrd(bags, path: Path, lab, force: bool = False) -> str:
    try:  # rerun-sdk is an optional extra: imported only when a recording is asked for
        from equidiff_core.viz.bag_to_rrd import convert_bags
    except ImportError as err:  # rerun-sdk is an optional extra
        print(f"[twin] no rerun recording: {err}", file=sys.stderr)
        return ""
    try:
        convert_bags(bags, path, lab, force=force)
    except Exception as err:  # noqa: BLE001 - a viz failure must not lose the run's results
        print(f"[twin] rerun conversion failed: {err}", file=sys.stderr)
        return ""
    return str(path)
