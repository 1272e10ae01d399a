"""`equidiff viz`: rerun view of the live graph, or recorded bags converted to .rrd.

equidiff viz                         # live, spawns a local viewer
equidiff viz --connect 10.0.0.5:9876 # live, streams to a viewer on another machine
equidiff viz -o eval.rrd             # live, headless: writes a file (open it later with `rerun eval.rrd`)
equidiff viz bags/ -o all.rrd        # every bag in bags/ as one recording with an `episode` timeline
equidiff viz bags/ -o rrd/ --per-episode   # one <bag>.rrd per episode
equidiff viz bags/episode_0003 --spawn     # look at a bag right away

OUT is written beside itself and renamed into place once complete; an existing OUT is refused
(exit 2) unless --force, which replaces it only then. Nothing converted: OUT is left as it was.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from equidiff_ros.commands import add_force_argument
from equidiff_ros.viz_job import run_viz


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.epilog = __doc__.split("\n", 1)[1]
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument(
        "bags",
        nargs="*",
        metavar="BAG",
        help="bag directories (or folders of bags) to convert; none: visualise the live graph",
    )
    sink = parser.add_mutually_exclusive_group()
    sink.add_argument("--spawn", action="store_true", help="spawn a local rerun viewer (live default with a display)")
    sink.add_argument("--connect", metavar="ADDR", help="stream to a running viewer (host:port or rerun+http URL)")
    sink.add_argument(
        "-o",
        "--output",
        metavar="OUT",
        type=Path,
        help="FILE.rrd to write (live headless, or bag conversion); a directory with --per-episode",
    )
    parser.add_argument("--per-episode", action="store_true", help="bags: one .rrd per episode in the OUT directory")
    parser.add_argument("--clouds", action="store_true", help="also show the raw camera clouds (throttled, strided)")
    parser.add_argument("--lab-config", type=Path, default=None, help="lab.yaml (default: the installed one)")
    parser.add_argument("--viz-config", type=Path, default=None, help="viz.yaml (default: config/viz.yaml)")
    parser.add_argument("--duration", type=float, default=None, metavar="S", help="live: stop after S seconds")
    add_force_argument(parser)


def run(args: argparse.Namespace) -> int:
    return run_viz(args)
