"""`equidiff dataset pack BAGS... --out DIR`: one compressed ``.episode.npz`` per bag, for training elsewhere.

    equidiff dataset pack demos/ --out packed/        # 40 twin demos: 401 MB of bags -> a few MB
    equidiff train packed/ --out runs/x --device cuda  # on the GPU machine, no bags needed

A packed episode holds exactly what training decodes from the bag (sparse voxel grids, TCP
states, the executed command schedule, the episode's metadata), so ``equidiff train`` and
``equidiff dataset stats`` accept it wherever they accept a bag. Bad bags are listed with the
reason and make the command exit 1, as with ``dataset stats``.

Each file is named after its bag's path below the bags' common folder (``day1/pick_0000`` and
``day2/pick_0000`` -> ``day1__pick_0000.episode.npz``, ``day2__pick_0000.episode.npz``); "packed"
counts the files in DIR. DIR is written beside itself and renamed into place once every bag is
packed: an existing DIR is refused (exit 2) unless ``--force``, which replaces it only then.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from equidiff_core.config import default_config_dir, load_lab_config
from equidiff_core.data.dataset import pack_episodes
from equidiff_core.data.episode_arrays import DatasetConfig
from equidiff_core.perception.observation import STATE_TOLERANCE_S
from equidiff_core.runtime.output_files import OutputExistsError
from equidiff_ros.commands import add_force_argument


def add_arguments(parser) -> None:
    parser.epilog = __doc__.split("\n", 1)[1]
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("bags", nargs="+", help="bag directories, or folders holding bag directories")
    parser.add_argument("--out", type=Path, required=True, help="directory for the packed episodes")
    parser.add_argument(
        "--tolerance", type=float, default=STATE_TOLERANCE_S, help="state/voxel stamp tolerance, s (as train)"
    )
    parser.add_argument(
        "--lab-config", help="lab.yaml (the workspace every grid must be on); default: the installed one"
    )
    add_force_argument(parser)


def run(args) -> int:
    lab = load_lab_config(args.lab_config or default_config_dir() / "lab.yaml")
    cfg = DatasetConfig.for_lab(lab, state_tolerance_s=args.tolerance)
    try:
        written, skipped = pack_episodes(args.bags, args.out, cfg, force=args.force)
    except OutputExistsError as err:
        print(f"equidiff dataset pack: {err}", file=sys.stderr)
        return 2
    for path, reason in skipped:
        print(f"SKIPPED {path}: {reason}")
    size = sum(f.stat().st_size for f in written)
    print(
        json.dumps(
            {"packed": len(written), "skipped": len(skipped), "out": str(args.out), "megabytes": round(size / 1e6, 2)}
        )
    )
    return 1 if skipped else 0
