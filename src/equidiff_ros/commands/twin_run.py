"""`equidiff twin run`: the main job. The whole stack end to end in the digital twin, no hardware.

    equidiff twin run --episodes 10                 # shipped checkpoint, new random scenes
    equidiff twin run --smoke                       # 1 short episode (CI): plumbing only
    equidiff twin run --checkpoint runs/x/policy.pt --episodes 20 --seed 5000

Brings up, as separate ROS 2 processes on a private ROS_DOMAIN_ID: twin_node (franky-sim +
scene), three camera_nodes (backend twin), voxel_node, policy_node, franka_node (connected to
the twin like to a real FR3) and recorder_node. Each episode: home the arm, reset the scene to a
new seed, record, let the policy act at 5 Hz until the block rests in the bowl or time runs out.
Writes one bag per episode and one rerun recording; prints a summary and, last, one JSON line
(episodes, success_rate, inference_p95_ms, end_to_end_p95_ms, dropped_cycles, clock,
latency_budget_ms, wall_s, ...). Ctrl-C or any node failure stops every process.

By default the twin runs on simulated time: twin_node publishes /clock, every node runs with
use_sim_time, and the sim waits for camera frames and for each observation's chunk, which
takes effect at the observation's time + --latency-ms (the budget of a lab machine; 100 ms).
The run then measures the policy, not this machine. --realtime runs on the wall clock instead
(only where the machine holds real time: a run whose sim fell below 0.9x is flagged).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from equidiff_core.twin.config import EVALUATION_FIRST_SEED

SHIPPED_NAME = Path("checkpoints") / "twin_compact" / "policy.pt"


def add_precision_argument(parser: argparse.ArgumentParser) -> None:
    """The policy's arithmetic in the twin (``twin.config.TWIN_PRECISION`` unless asked otherwise)."""
    from equidiff_core.twin.config import TWIN_PRECISION

    parser.add_argument(
        "--precision",
        choices=("fp32", "bf16", "auto"),
        default=TWIN_PRECISION,
        help=f"policy arithmetic (default {TWIN_PRECISION} on every machine; auto: bf16 where the CPU has "
        "native bf16, so results would depend on the CPU)",
    )


def shipped_checkpoint() -> Path:
    """The checkpoint shipped in the repository (source checkout, or share/equidiff_ros when installed)."""
    from equidiff_core.config import default_config_dir

    candidates = [Path(__file__).resolve().parents[3] / SHIPPED_NAME, default_config_dir().parent / SHIPPED_NAME]
    return next((c for c in candidates if c.is_file()), candidates[0])


SHIPPED_CHECKPOINT = shipped_checkpoint()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.epilog = __doc__.split("\n", 1)[1]
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("--episodes", type=int, default=5)
    parser.add_argument(
        "--seed", type=int, default=EVALUATION_FIRST_SEED, help="first episode's scene seed (then +1 each)"
    )
    parser.add_argument(
        "--checkpoint",
        type=Path,
        default=None,
        help=f"exported policy file (default: the shipped {SHIPPED_CHECKPOINT.parent.name})",
    )
    parser.add_argument(
        "--standin",
        action="store_true",
        help="use an untrained stand-in policy (plumbing test; success is meaningless)",
    )
    parser.add_argument("--out", type=Path, default=None, help="output directory (default: runs/twin_run_<time>)")
    parser.add_argument("--max-duration", type=float, default=None, help="seconds per episode (twin.yaml's default)")
    parser.add_argument("--smoke", action="store_true", help="1 episode of a few seconds (CI)")
    parser.add_argument("--domain", type=int, default=None, help="ROS_DOMAIN_ID (default: a random private one)")
    parser.add_argument("--device", default="cpu", help="policy device: cpu | cuda | auto")
    add_precision_argument(parser)
    parser.add_argument("--lab-config", type=Path, default=None)
    parser.add_argument("--twin-config", type=Path, default=None)
    parser.add_argument("--record-clouds", action="store_true", help="also record the three camera clouds")
    parser.add_argument("--no-rrd", action="store_true", help="skip the rerun recording")
    parser.add_argument(
        "--attach", action="store_true", help="run the episodes against nodes already running (launch/twin.launch.py)"
    )
    parser.add_argument(
        "--lenient",
        action="store_true",
        help="with --realtime: accept observations up to 4 s old (overloaded machines)",
    )
    parser.add_argument(
        "--clock",
        choices=("sim", "realtime"),
        default="sim",
        help="sim: simulated time, in lockstep with the pipeline (default); realtime: the wall clock",
    )
    parser.add_argument(
        "--realtime",
        dest="clock",
        action="store_const",
        const="realtime",
        help="the same as --clock realtime (machines that hold real time)",
    )
    parser.add_argument(
        "--latency-ms",
        type=float,
        default=100.0,
        help="simulated time: the latency budget L; a chunk takes effect at its observation + L",
    )
    parser.add_argument(
        "--stall-timeout",
        type=float,
        default=30.0,
        help="simulated time: wall seconds the sim waits for a camera or the policy before the episode ends as stalled",
    )
    parser.add_argument(
        "--composed",
        action="store_true",
        help="run every node but twin_node in one process (one MultiThreadedExecutor)",
    )


def resolve_policy(args, out: Path, workspace, cfg) -> tuple[Path, str]:
    from equidiff_core.twin.standin import STANDIN_LABEL, make_standin_policy

    if args.checkpoint is not None or args.attach:
        if args.checkpoint is None or not args.checkpoint.is_file():
            raise FileNotFoundError(f"--checkpoint {args.checkpoint}: no such file")
        return args.checkpoint, str(args.checkpoint)
    if not args.standin and not args.smoke and SHIPPED_CHECKPOINT.is_file():
        return SHIPPED_CHECKPOINT, f"shipped {SHIPPED_NAME}"
    if not args.standin and not args.smoke:
        raise FileNotFoundError(f"no shipped checkpoint at {SHIPPED_CHECKPOINT}; pass --checkpoint or --standin")
    path = make_standin_policy(
        out / "standin_policy.pt", workspace, preset="tiny" if args.smoke else "compact", cfg=cfg
    )
    return path, STANDIN_LABEL


def run(args: argparse.Namespace) -> int:
    from equidiff_core.config import ConfigError
    from equidiff_core.twin.config import load_twin_job_configs
    from equidiff_core.twin.metrics import RunSummary
    from equidiff_core.twin.processes import NodeProcessError
    from equidiff_ros.twin import (
        SupervisorError,
        TwinStack,
        run_policy_episode,
    )

    try:
        configs = load_twin_job_configs(args.lab_config, args.twin_config)
    except ConfigError as err:
        print(f"equidiff twin run: {err}", file=sys.stderr)
        return 2
    lab_path, twin_path, lab, cfg = configs.lab_path, configs.twin_path, configs.lab, configs.twin
    episodes = 1 if args.smoke else args.episodes
    max_duration = args.max_duration or (8.0 if args.smoke else cfg.episode.max_duration_s)
    out = args.out or Path("runs") / time.strftime("twin_run_%Y%m%d_%H%M%S")
    out.mkdir(parents=True, exist_ok=True)
    try:
        policy_path, policy_label = resolve_policy(args, out, lab.workspace, cfg)
    except FileNotFoundError as err:
        print(f"equidiff twin run: {err}", file=sys.stderr)
        return 2
    clock = args.clock
    args.realtime = clock == "realtime"
    print(
        f"[twin] policy: {policy_label}; {episodes} episode(s) of at most {max_duration:.0f} s; output {out}; "
        + ("real time" if args.realtime else f"simulated time, latency budget {args.latency_ms:.0f} ms")
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
            lenient=args.lenient or (args.smoke and args.realtime),
            attach=args.attach,
            realtime=args.realtime,
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
        latency_budget_ms=None if args.realtime else args.latency_ms,
        wall_s=time.monotonic() - wall_start,
    )
    if not args.no_rrd and records:
        summary.rrd = write_rrd([r.bag for r in records if r.bag], out / "twin_run.rrd", lab)
    print(summary.human())
    (out / "summary.json").write_text(summary.json_line() + "\n")
    print(summary.json_line())
    return 0


def write_rrd(bags, path: Path, lab) -> str:
    try:
        from equidiff_core.viz.bag_to_rrd import convert_bags
    except ImportError as err:  # rerun-sdk is an optional extra
        print(f"[twin] no rerun recording: {err}", file=sys.stderr)
        return ""
    try:
        convert_bags(bags, path, lab)
    except Exception as err:  # noqa: BLE001 - a viz failure must not lose the run's results
        print(f"[twin] rerun conversion failed: {err}", file=sys.stderr)
        return ""
    return str(path)
