"""`equidiff twin run`: the main job. The whole stack end to end in the digital twin, no hardware.

    equidiff twin run --episodes 10                 # shipped checkpoint, new random scenes
    equidiff twin run --smoke                       # 1 short episode (CI): plumbing only
    equidiff twin run --checkpoint runs/x/policy.pt --episodes 20 --seed 5000

Brings up, as separate ROS 2 processes on a private ROS_DOMAIN_ID: twin_node (franky-sim +
scene), three camera_nodes (backend twin), voxel_node, policy_node, franka_node (connected to
the twin like to a real FR3) and recorder_node. Each episode: home the arm, reset the scene to a
new seed, record, let the policy act at 5 Hz until the block rests in the bowl or time runs out.
Writes one bag per episode and one rerun recording; prints a summary and, last, one JSON line
(episodes, success_rate, inference_p95_ms, end_to_end_p95_ms, dropped_cycles, ...).
Ctrl-C or any node failure stops every process.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

SHIPPED_NAME = Path("checkpoints") / "twin_compact" / "policy.pt"


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
    parser.add_argument("--seed", type=int, default=100_000, help="first episode's scene seed (then +1 each)")
    parser.add_argument("--checkpoint", type=Path, default=None,
                        help=f"exported policy file (default: the shipped {SHIPPED_CHECKPOINT.parent.name})")
    parser.add_argument("--standin", action="store_true",
                        help="use an untrained stand-in policy (plumbing test; success is meaningless)")
    parser.add_argument("--out", type=Path, default=None, help="output directory (default: runs/twin_run_<time>)")
    parser.add_argument("--max-duration", type=float, default=None, help="seconds per episode (twin.yaml's default)")
    parser.add_argument("--smoke", action="store_true", help="1 episode of a few seconds (CI)")
    parser.add_argument("--domain", type=int, default=None, help="ROS_DOMAIN_ID (default: a random private one)")
    parser.add_argument("--device", default="cpu", help="policy device: cpu | cuda | auto")
    parser.add_argument("--lab-config", type=Path, default=None)
    parser.add_argument("--twin-config", type=Path, default=None)
    parser.add_argument("--record-clouds", action="store_true", help="also record the three camera clouds")
    parser.add_argument("--no-rrd", action="store_true", help="skip the rerun recording")
    parser.add_argument("--attach", action="store_true",
                        help="run the episodes against nodes already running (launch/twin.launch.py)")
    parser.add_argument("--lenient", action="store_true",
                        help="accept observations up to 4 s old (overloaded CI machines; default with --smoke)")


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
    path = make_standin_policy(out / "standin_policy.pt", workspace, preset="tiny" if args.smoke else "compact",
                               cfg=cfg)
    return path, STANDIN_LABEL


def run_episode(stack, seed: int, max_duration_s: float, rate_hz: float):
    from equidiff_core.twin.metrics import EpisodeRecord, count_dropped_cycles

    sup, cfg = stack.sup, stack.cfg
    rec = EpisodeRecord(seed=seed)
    stack.home()
    sup.reset_scene(seed, check=stack.check)
    time.sleep(0.6)  # let cameras and voxels show the new scene before the policy sees it
    status = sup.recorder(f"start {stack.task}", "recording", check=stack.check)
    rec.bag = status.split(" ", 1)[1] if " " in status else ""
    sup.open_gate()
    gate_t = time.monotonic()
    try:
        sup.wait_for(lambda: sup.chunk_arrivals, 60.0, "the first policy chunk", stack.check)
        start = sup.chunk_arrivals[0]
        success_since = None
        while time.monotonic() - start < max_duration_s:
            stack.check()
            if sup.twin().get("success"):
                success_since = success_since or time.monotonic()
                if time.monotonic() - success_since >= cfg.success.hold_s:
                    rec.success = True
                    break
            else:
                success_since = None
            time.sleep(0.05)
        end = time.monotonic()
    finally:
        arrivals, e2e, inf = sup.close_gate()
    rec.duration_s = round((success_since or end) - start, 2) if arrivals else round(time.monotonic() - gate_t, 2)
    rec.chunks = len(arrivals)
    rec.dropped_cycles = count_dropped_cycles(arrivals, start, end, rate_hz)
    rec.end_to_end_ms, rec.inference_ms = e2e, inf
    pose, width = sup.current()
    sup.send_target(pose, width)  # hold where it is while the recorder closes
    sup.recorder(f"stop {'success' if rec.success else 'failure'} seed={seed}", "idle", check=stack.check)
    return rec


def run(args: argparse.Namespace) -> int:
    from equidiff_core.config import ConfigError
    from equidiff_core.twin.config import load_twin_job_configs
    from equidiff_core.twin.metrics import RunSummary
    from equidiff_core.twin.processes import NodeProcessError
    from equidiff_ros.twin_supervisor import SupervisorError, TwinStack

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
    print(f"[twin] policy: {policy_label}; {episodes} episode(s) of at most {max_duration:.0f} s; output {out}")
    records = []
    sim_rates = []
    try:
        with TwinStack(out, lab_path, twin_path, policy=str(policy_path), domain_id=args.domain, task="twin_eval",
                       device=args.device, seed=args.seed, record_clouds=args.record_clouds,
                       lenient=args.lenient or args.smoke, attach=args.attach) as stack:
            for i in range(episodes):
                missed = stack.sup.twin().get("missed_commands", 0)
                rec = run_episode(stack, args.seed + i, max_duration, lab.observation_hz)
                state = stack.sup.twin()
                sim_rates.append(state.get("steps_per_s", 0.0) / 1000.0)
                records.append(rec)
                print(f"[twin] episode {i + 1}/{episodes} seed {rec.seed}: "
                      f"{'success' if rec.success else 'failure'} in {rec.duration_s:.1f} s, {rec.chunks} chunks, "
                      f"{state.get('missed_commands', 0) - missed} ms of stale robot commands")
    except KeyboardInterrupt:
        print("[twin] interrupted: all nodes stopped", file=sys.stderr)
        if not records:
            return 130
    except (NodeProcessError, SupervisorError) as err:
        print(f"equidiff twin run: {err}", file=sys.stderr)
        return 1
    summary = RunSummary(records, sim_rate=sum(sim_rates) / len(sim_rates) if sim_rates else None,
                         policy=policy_label)
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
