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


def resolve_policy(
    out: Path,
    workspace,
    cfg,
    *,
    checkpoint: Path | None = None,
    attach: bool = False,
    standin: bool = False,
    standin_preset: str = "compact",
) -> tuple[Path, str]:
    """The policy file a twin job runs and its label: ``checkpoint``, else the shipped one, else (``standin``) an
    untrained stand-in of ``standin_preset`` written into ``out``; FileNotFoundError when the one asked for (a
    checkpoint, which ``attach`` requires, or the shipped one) is missing."""
    if checkpoint is not None or attach:
        if checkpoint is None or not checkpoint.is_file():
            raise FileNotFoundError(f"--checkpoint {checkpoint}: no such file")
        return checkpoint, str(checkpoint)
    if not standin and SHIPPED_CHECKPOINT.is_file():
        return SHIPPED_CHECKPOINT, f"shipped {SHIPPED_NAME}"
    if not standin:
        raise FileNotFoundError(f"no shipped checkpoint at {SHIPPED_CHECKPOINT}; pass --checkpoint or --standin")
    path = make_standin_policy(out / "standin_policy.pt", workspace, preset=standin_preset, cfg=cfg)
    return path, STANDIN_LABEL
