"""Policy files on disk: the exported plain-torch policy's format, checked loading, atomic saving.

An exported policy is one ``torch.load(weights_only=True)`` file: plain torch weights and a JSON
config (``export_policy``); training checkpoints are read with the same checks
(``load_checked``). Missing, corrupt or incompatible files raise ``CheckpointError`` with the
reason. ``inference.load_inference_policy`` builds the runnable policy from such a file.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import torch

from .models import action_space
from .output_files import staged_output
from .presets import PolicyPreset

FORMAT = "equidiff_policy"
VERSION = 1


class CheckpointError(RuntimeError):
    """A policy/checkpoint file that is missing, corrupt, or not loadable by this version."""


def export_policy(policy, path: str | Path) -> Path:
    """Write ``policy`` (a policies.DiffusionPolicy with its normaliser set) as a plain-torch inference file."""
    if policy.normalizer is None:
        raise CheckpointError("cannot export a policy without a normaliser")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    plain = policy.model.export_plain()
    state = {
        k: v.detach().to("cpu", torch.float32).contiguous() if v.is_floating_point() else v.detach().cpu()
        for k, v in plain.state_dict().items()
    }
    payload = {
        "format": FORMAT,
        "version": VERSION,
        "config_json": json.dumps(policy.config_dict()),
        "state_dict": state,
    }
    return save_atomically(payload, path)


def save_atomically(obj: Any, path: Path) -> Path:
    """``torch.save`` through a temporary file beside ``path``, which it replaces: a killed writer never
    leaves a half-written ``path`` (checkpoints are rewritten in place on purpose)."""
    with staged_output(path, force=True) as staged:
        torch.save(obj, staged.path)
    return path


def build_plain_network(policy_name: str, preset: PolicyPreset) -> torch.nn.Module:
    freqs = action_space.freqs_for(preset.control)
    if policy_name == "equidiff":
        from .models.plain import PlainEquiNoisePredictor

        return PlainEquiNoisePredictor(preset, freqs)
    if policy_name == "baseline":
        from .models.baseline import BaselineNoisePredictor

        return BaselineNoisePredictor(preset, freqs)
    raise CheckpointError(f"unknown policy kind {policy_name!r} in checkpoint")


def load_checked(path: str | Path, file_format: str, version: int, kind: str, what: str) -> dict:
    """The dict saved at ``path``, checked to be a ``kind`` ("policy file", "checkpoint") of ``file_format``
    and ``version``; else a ``CheckpointError`` naming the path and what is wrong (``what``: what the file
    should have been, e.g. "an exported equidiff policy"). Policy files and training checkpoints both."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: no such {kind}")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:
        raise CheckpointError(
            f"{path}: not a readable {kind} ({type(err).__name__}: {(str(err).splitlines() or [''])[0]})"
        ) from err
    if not isinstance(payload, dict) or payload.get("format") != file_format:
        found = payload.get("format") if isinstance(payload, dict) else type(payload).__name__
        raise CheckpointError(f"{path}: not {what} (format {found!r})")
    if payload.get("version") != version:
        raise CheckpointError(f"{path}: {kind} version {payload.get('version')} is not supported (expected {version})")
    return payload


def read_policy_file(path: str | Path) -> tuple[dict, dict]:
    """(config, state_dict) of an exported policy file, validated."""
    payload = load_checked(path, FORMAT, VERSION, "policy file", "an exported equidiff policy")
    try:
        config = json.loads(payload["config_json"])
        state = payload["state_dict"]
    except (KeyError, TypeError, json.JSONDecodeError) as err:
        raise CheckpointError(f"{path}: malformed policy file: {err}") from err
    return config, state


def check_device(device: str) -> None:
    """A ValueError naming why ``device`` cannot run the policy here (CUDA missing), not torch's
    assertion deep inside the first ``.to()``."""
    if str(device).startswith("cuda") and not torch.cuda.is_available():
        build = f"torch {torch.__version__}, " + (
            "built without CUDA" if torch.version.cuda is None else f"CUDA {torch.version.cuda}, no GPU visible"
        )
        raise ValueError(f"device {device!r} requested but CUDA is not available ({build}); use --device cpu")
