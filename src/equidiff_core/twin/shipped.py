"""The policy checkpoint shipped in the repository, and which policy a twin job runs (shipped, given or stand-in)."""

from __future__ import annotations

from pathlib import Path

from equidiff_core.config import default_config_dir
from equidiff_core.twin.standin import STANDIN_LABEL, make_standin_policy

SHIPPED_NAME = Path("checkpoints") / "twin_compact" / "policy.pt"


def shipped_checkpoint() -> Path:
    """The checkpoint shipped in the repository (source checkout, or share/equidiff_ros when installed)."""
    candidates = [Path(__file__).resolve().parents[3] / SHIPPED_NAME, default_config_dir().parent / SHIPPED_NAME]
    return next((c for c in candidates if c.is_file()), candidates[0])


SHIPPED_CHECKPOINT = shipped_checkpoint()


def resolve_policy(args, out: Path, workspace, cfg) -> tuple[Path, str]:
    """The policy file a twin job runs and its label: ``--checkpoint``, else the shipped one, else (``--standin``,
    ``--smoke``) an untrained stand-in written into ``out``; FileNotFoundError when the one asked for is missing."""
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
