"""`equidiff bags repair BAG...`: recover a bag whose recorder was killed before closing it,
or whose bytes were damaged afterwards (a chunk CRC mismatch).

Rebuilds metadata.yaml and the MCAP summary from every intact chunk and prints one ``dropped``
line per damaged chunk (its topics, time range and message counts); the damaged original is
kept as ``<bag>.unrepaired`` (or left untouched with ``--output``). Healthy bags are left alone.
"""

from __future__ import annotations

import sys

from equidiff_core.data.bags import repair_bag
from equidiff_core.data.mcap_reader import BagError


def add_arguments(parser) -> None:
    parser.add_argument("bags", nargs="+", help="bag directories (each holding one .mcap)")
    parser.add_argument("--output", help="write the repaired bag here instead of in place (one bag only)")
    parser.add_argument("--force", action="store_true", help="rewrite even if the bag reads fine")


def run(args) -> int:
    if args.output and len(args.bags) != 1:
        print("equidiff bags repair: --output takes exactly one bag", file=sys.stderr)
        return 2
    failed = 0
    for bag in args.bags:
        try:
            report = repair_bag(bag, output=args.output, force=args.force)
        except BagError as err:
            print(f"FAILED {bag}: {err}", file=sys.stderr)
            failed += 1
            continue
        if report is None:
            print(f"ok {bag}: readable as is, nothing to repair")
            continue
        kept = f"; original kept at {report.original}" if report.original else ""
        counts = ", ".join(f"{t} {n}" for t, n in sorted(report.messages.items()))
        print(
            f"repaired {report.path}: {report.total} messages in {report.chunks} chunks ({counts}); "
            f"stopped at {report.reason}, {report.dropped_bytes} bytes lost{kept}"
        )
        for line in report.dropped():
            print(f"  {line}")
    return 1 if failed else 0
