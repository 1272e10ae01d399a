"""`equidiff dataset pack BAGS... --out DIR`: one compressed ``.episode.npz`` per bag, for training elsewhere.

    equidiff dataset pack demos/ --out packed/        # 40 twin demos: 401 MB of bags -> a few MB
    equidiff train packed/ --out runs/x --device cuda  # on the GPU machine, no bags needed

A packed episode holds exactly what training decodes from the bag (sparse voxel grids, TCP
states, the executed command schedule, the episode's metadata), so ``equidiff train`` and
``equidiff dataset stats`` accept it wherever they accept a bag. Bad bags are listed with the
reason and make the command exit 1, as with ``dataset stats``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from equidiff_core.config import default_config_dir, load_lab_config
from equidiff_core.dataset import DatasetConfig, pack_episodes
from equidiff_core.observation import STATE_TOLERANCE_S


def add_arguments(parser) -> None:
    parser.epilog = __doc__.split("\n", 1)[1]
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("bags", nargs="+", help="bag directories, or folders holding bag directories")
    parser.add_argument("--out", type=Path, required=True, help="directory for the packed episodes")
    parser.add_argument(
        "--tolerance", type=float, default=STATE_TOLERANCE_S, help="state/voxel stamp tolerance, s (as train)"
    )
    parser.add_argument("--lab-config", help="lab.yaml (its workspace resolution); default: the installed one")


def run(args) -> int:
    lab = load_lab_config(args.lab_config or default_config_dir() / "lab.yaml")
    cfg = DatasetConfig(resolution=lab.workspace.resolution, state_tolerance_s=args.tolerance)
    written, skipped = pack_episodes(args.bags, args.out, cfg)
    for path, reason in skipped:
        print(f"SKIPPED {path}: {reason}")
    size = sum(f.stat().st_size for f in written)
    print(
        json.dumps(
            {"packed": len(written), "skipped": len(skipped), "out": str(args.out), "megabytes": round(size / 1e6, 2)}
        )
    )
    return 1 if skipped else 0
