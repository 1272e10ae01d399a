"""Policy files on disk: the exported plain-torch policy's format, checked loading, atomic saving.

An exported policy is one ``torch.load(weights_only=True)`` file: plain torch weights, a JSON
config and the sha256 of the weights (``export_policy``, ``weights_sha256``); training
checkpoints carry the hash of their model weights too and are read with the same checks
(``load_checked``). Each failure raises ``CheckpointError`` naming what it is: missing,
truncated or unreadable, another format (``CheckpointFormatError``), an unknown version, or
weights that no longer match their hash. A file written before the hash existed loads and is
reported as unhashed (``PolicyFile.weights_sha256`` is None; ``equidiff check ...`` print
``"weights_sha256": "unhashed"``). ``policy.inference.load_inference_policy`` builds the runnable
policy from such a file.
"""

from __future__ import annotations

import hashlib
import json
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from ..models import action_space
from ..models.sampling import check_sampler_entry
from ..runtime.output_files import staged_output
from .presets import PolicyPreset

FORMAT = "equidiff_policy"
VERSION = 1


HASH_KEY = "weights_sha256"
DOUBT_KEY = "doubt_json"  # optional: the doubt gate's calibration (with_doubt_calibration); older files lack it
UNHASHED = "unhashed"  # what reports print for a file written before policy files carried a hash
KNOWN_FORMATS = {FORMAT: "an exported equidiff policy", "equidiff_train_ckpt": "an equidiff training checkpoint"}


class CheckpointError(RuntimeError):
    """A policy/checkpoint file that is missing, truncated, altered (hash mismatch), of an unknown
    version, or not loadable by this version; the message says which."""


class CheckpointFormatError(CheckpointError):
    """A readable file of another format (e.g. a training checkpoint where a policy file was expected):
    the one failure where trying the other loader makes sense."""


@dataclass(frozen=True)
class PolicyFile:
    config: dict
    state: dict
    weights_sha256: str | None  # checked against the weights at load; None: an old, unhashed file
    doubt: dict | None = None  # the doubt gate's calibration (policy.doubt.DoubtCalibration); None: none stored


def weights_sha256(state: dict) -> str:
    """sha256 over a state dict in a canonical order: per key (sorted), its name, dtype, shape and raw
    bytes. The same weights give the same hash bit for bit, whatever the dict's order or the device."""
    digest = hashlib.sha256()
    for key in sorted(state):
        value = state[key]
        digest.update(key.encode() + b"\0")
        if isinstance(value, torch.Tensor):
            t = value.detach().cpu().contiguous()
            digest.update(f"{t.dtype}{tuple(t.shape)}".encode() + b"\0")
            digest.update(t.reshape(-1).view(torch.uint8).numpy().tobytes())
        else:  # not expected in a state dict, but hashed rather than skipped
            digest.update(repr(value).encode() + b"\0")
    return digest.hexdigest()


def export_policy(policy, path: str | Path, sampler: dict | None = None) -> Path:
    """Write ``policy`` (a diffusion.DiffusionPolicy with its normaliser set) as a plain-torch inference file;
    ``sampler`` ({"steps", "timestep_spacing"} or {"steps", "timesteps"}) becomes the file's own DDIM sampler
    (``inference.load_inference_policy``), as a distilled policy needs; checked here, so that no file is written
    that would not load."""
    if policy.normalizer is None:
        raise CheckpointError("cannot export a policy without a normaliser")
    if sampler:
        try:
            check_sampler_entry(policy.preset, sampler)
        except (ValueError, TypeError) as err:
            raise CheckpointError(f"sampler {sampler}: {err}") from err
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
        "config_json": json.dumps({**policy.config_dict(), **({"sampler": sampler} if sampler else {})}),
        "state_dict": state,
        HASH_KEY: weights_sha256(state),
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
        from ..models.plain import PlainEquiNoisePredictor

        return PlainEquiNoisePredictor(preset, freqs)
    if policy_name == "baseline":
        from ..models.baseline import BaselineNoisePredictor

        return BaselineNoisePredictor(preset, freqs)
    raise CheckpointError(f"unknown policy kind {policy_name!r} in checkpoint")


def load_checked(
    path: str | Path, file_format: str, version: int, kind: str, what: str, weights_key: str | None = None
) -> dict:
    """The dict saved at ``path``, checked to be a ``kind`` ("policy file", "checkpoint") of ``file_format``
    and ``version``, with ``payload[weights_key]`` matching its stored ``weights_sha256`` (when the file has
    one); else a ``CheckpointError`` naming the path and what is wrong (``what``: what the file should have
    been, e.g. "an exported equidiff policy"). Policy files and training checkpoints both."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: no such {kind}")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:
        first = (str(err).splitlines() or [""])[0]
        if not zipfile.is_zipfile(path):  # torch files are zip archives; a cut one has no directory at its end
            raise CheckpointError(
                f"{path}: not a readable {kind}: truncated or not a torch file "
                f"({path.stat().st_size} bytes, no zip directory at its end; "
                f"{type(err).__name__}: {first})"
            ) from err
        raise CheckpointError(f"{path}: not a readable {kind}: corrupt ({type(err).__name__}: {first})") from err
    if not isinstance(payload, dict) or payload.get("format") != file_format:
        found = payload.get("format") if isinstance(payload, dict) else type(payload).__name__
        known = f": it is {KNOWN_FORMATS[found]}" if found in KNOWN_FORMATS else ""
        raise CheckpointFormatError(f"{path}: not {what} (format {found!r}{known})")
    if payload.get("version") != version:
        raise CheckpointError(
            f"{path}: {what} of version {payload.get('version')!r}, which this equidiff cannot read "
            f"(it reads version {version}; written by a newer equidiff?)"
        )
    stored = payload.get(HASH_KEY)
    if stored is not None and weights_key is not None:
        weights = payload.get(weights_key)
        actual = weights_sha256(weights) if isinstance(weights, dict) else None
        if actual != stored:
            raise CheckpointError(
                f"{path}: weights do not match their stored sha256 (stored {stored}, computed {actual}): "
                f"the {kind} was altered or damaged after it was written"
            )
    return payload


def open_policy_file(path: str | Path) -> PolicyFile:
    """An exported policy file, validated (format, version, weights hash)."""
    payload = load_checked(path, FORMAT, VERSION, "policy file", "an exported equidiff policy", "state_dict")
    try:
        config = json.loads(payload["config_json"])
        state = payload["state_dict"]
    except (KeyError, TypeError, json.JSONDecodeError) as err:
        raise CheckpointError(f"{path}: malformed policy file: {err}") from err
    doubt = payload.get(DOUBT_KEY)
    try:
        doubt = None if doubt is None else json.loads(doubt)
    except (TypeError, json.JSONDecodeError) as err:
        raise CheckpointError(f"{path}: malformed doubt calibration: {err}") from err
    return PolicyFile(config, state, payload.get(HASH_KEY), doubt)


def with_doubt_calibration(path: str | Path, calibration: dict, out: str | Path, force: bool = False) -> Path:
    """A copy of the policy file at ``path`` with ``calibration`` (``DoubtCalibration.as_dict``) stored in it,
    written to ``out`` (refused if it exists unless ``force``; it may be ``path`` itself); weights untouched."""
    payload = load_checked(path, FORMAT, VERSION, "policy file", "an exported equidiff policy", "state_dict")
    payload[DOUBT_KEY] = json.dumps(calibration)
    with staged_output(out, force=force) as staged:
        torch.save(payload, staged.path)
    return Path(out)


def read_policy_file(path: str | Path) -> tuple[dict, dict]:
    """(config, state_dict) of an exported policy file, validated."""
    policy_file = open_policy_file(path)
    return policy_file.config, policy_file.state


def rewrite_with_hash(path: str | Path, out: str | Path | None = None, weights_key: str = "state_dict") -> str:
    """Store the sha256 of ``payload[weights_key]`` in the torch file at ``path`` (written before files
    carried one), everything else unchanged; returns the hash. Loads with ``weights_only=True``."""
    path = Path(path)
    payload = torch.load(path, map_location="cpu", weights_only=True)
    if not isinstance(payload, dict) or not isinstance(payload.get(weights_key), dict):
        raise CheckpointError(f"{path}: no {weights_key!r} weights to hash")
    payload[HASH_KEY] = weights_sha256(payload[weights_key])
    save_atomically(payload, Path(out) if out else path)
    return payload[HASH_KEY]


def check_device(device: str) -> None:
    """A ValueError naming why ``device`` cannot run the policy here (CUDA missing), not torch's
    assertion deep inside the first ``.to()``."""
    if str(device).startswith("cuda") and not torch.cuda.is_available():
        build = f"torch {torch.__version__}, " + (
            "built without CUDA" if torch.version.cuda is None else f"CUDA {torch.version.cuda}, no GPU visible"
        )
        raise ValueError(f"device {device!r} requested but CUDA is not available ({build}); use --device cpu")
