"""``equidiff viz``: recorded bags converted to rerun, or the live graph viewed (the command's help text has
examples). Importable without rerun or rclpy: rerun is checked first and named if missing, and the live graph's
node (rclpy) is imported only in live mode."""

from __future__ import annotations

import os
import sys
from contextlib import nullcontext

from equidiff_core.config import ConfigError, default_config_dir, load_lab_config
from equidiff_core.runtime.output_files import OutputExistsError, staged_output
from equidiff_core.viz import VizUnavailable, require_rerun
from equidiff_core.viz.bag_to_rrd import BagConversionError, convert_bags
from equidiff_core.viz.logger import RerunLogger
from equidiff_core.viz.recording_setup import load_viz_config, open_recording


def _has_display() -> bool:
    return sys.platform == "darwin" or bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def run_viz(args) -> int:
    """``equidiff viz`` for its parsed arguments: bags converted, or the live graph viewed; the exit status."""
    try:
        require_rerun()
    except VizUnavailable as err:
        print(f"equidiff viz: {err}", file=sys.stderr)
        return 2
    try:
        lab = load_lab_config(args.lab_config or default_config_dir() / "lab.yaml")
        config = load_viz_config(args.viz_config)
    except ConfigError as err:
        print(f"equidiff viz: {err}", file=sys.stderr)
        return 2
    if args.clouds:
        config = type(config)(**{**config.__dict__, "clouds": True})
    if args.bags:
        return _convert(args, lab, config)
    return _live(args, lab, config)


def _convert(args, lab, config) -> int:
    to_viewer = args.spawn or args.connect is not None
    if args.output is None and not to_viewer:
        print(
            "equidiff viz: converting bags needs -o OUT.rrd (or -o DIR --per-episode), "
            "or --spawn / --connect ADDR to send them to a viewer",
            file=sys.stderr,
        )
        return 2
    if to_viewer and args.per_episode:
        print("equidiff viz: --per-episode writes files: use -o DIR", file=sys.stderr)
        return 2
    if args.spawn and not _has_display():
        print("equidiff viz: no display to spawn a viewer on; use -o FILE.rrd or --connect HOST:PORT", file=sys.stderr)
        return 2
    try:
        report = convert_bags(
            args.bags,
            args.output,
            lab,
            config,
            per_episode=args.per_episode,
            spawn=args.spawn,
            connect=args.connect,
            force=args.force,
        )
    except (BagConversionError, OutputExistsError) as err:
        print(f"equidiff viz: {err}", file=sys.stderr)
        return 2
    for ep in report.episodes:
        if ep.error:
            print(f"SKIPPED {ep.bag}: {ep.error}", file=sys.stderr)
            continue
        shown = ", ".join(f"{k} {v}" for k, v in sorted(ep.logged.items()))
        dropped = f"; dropped {ep.dropped}" if ep.dropped else ""
        print(f"{ep.bag.name}: {ep.messages} messages -> {ep.output or 'viewer'} ({shown}{dropped})")
        for warning in ep.warnings:
            print(f"  warning: {warning}", file=sys.stderr)
    if report.outputs:
        print(
            f"wrote {', '.join(map(str, report.outputs))} in {report.seconds:.1f} s; "
            f"open with: rerun {report.outputs[0]}"
        )
    elif not to_viewer:
        print("nothing converted", file=sys.stderr)
    return 0 if report.ok else 1


def _live(args, lab, config) -> int:
    if args.per_episode:
        print("equidiff viz: --per-episode only applies to bag conversion", file=sys.stderr)
        return 2
    spawn = args.spawn or (args.connect is None and args.output is None)
    if spawn and not _has_display():
        print(
            "equidiff viz: no display to spawn a viewer on; write a file with -o FILE.rrd "
            "or stream to a viewer elsewhere with --connect HOST:PORT",
            file=sys.stderr,
        )
        return 2
    if args.output is not None and args.output.suffix != ".rrd":
        print(f"equidiff viz: -o must name a .rrd file, got {args.output}", file=sys.stderr)
        return 2
    try:  # rclpy is needed for the live graph only: converting bags works without ROS
        from equidiff_ros.viz_node import run_live
    except ImportError as err:
        print(
            f"equidiff viz: live mode needs rclpy ({err}); install ROS 2 Jazzy or pip install 'equidiff_ros[ros]'",
            file=sys.stderr,
        )
        return 2
    try:  # a file lands when the viewing ends (Ctrl-C, --duration), never over an existing one without --force
        with staged_output(args.output, force=args.force) if args.output is not None else nullcontext() as staged:
            rec = open_recording("live", spawn=spawn, connect=args.connect, save=staged.path if staged else None)
            logger = RerunLogger(rec, lab, config)
            logger.log_static_scene()
            try:
                received = run_live(logger, lab, clouds=config.clouds, duration_s=args.duration)
            finally:
                rec.flush()
                rec.disconnect()
    except OutputExistsError as err:
        print(f"equidiff viz: {err}", file=sys.stderr)
        return 2
    for warning in logger.warnings:
        print(f"warning: {warning}", file=sys.stderr)
    dropped = f"; dropped {dict(logger.errors)} (last: {logger.last_error})" if logger.errors else ""
    print(f"received {received}; logged {dict(logger.logged)}{dropped}")
    if args.output is not None:
        print(f"wrote {args.output}; open with: rerun {args.output}")
    return 0
