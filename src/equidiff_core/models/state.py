"""A network's learned state, the same whichever train/eval mode it is in.

escnn layers cache the filter they expand from their weights as buffers (``filter``,
``expanded_bias``, ``matrix``) while in eval mode and drop them in train mode, so a plain
``state_dict()`` depends on the mode the model happened to be in: a checkpoint saved right after
validation carried the caches (the compact EquiDiff's weights grew from 6 to 17 MB), and one saved
between validations lacked keys that a freshly built model has, so a strict load refused it.
Saving in train mode and loading with the caches skipped makes the file independent of the mode.
"""

from __future__ import annotations

import contextlib

import torch

__all__ = ["learned_state_dict", "load_learned_state", "parameters_only", "refresh_escnn_caches"]

_ESCNN_CACHES = ("filter", "expanded_bias", "matrix")


@contextlib.contextmanager
def _train_mode(model: torch.nn.Module):
    was_training = model.training
    model.train(True)  # escnn drops its caches here
    try:
        yield
    finally:
        model.train(was_training)  # back to eval re-expands them from the (possibly new) weights


def refresh_escnn_caches(model: torch.nn.Module) -> None:
    """Re-expand escnn's eval-mode caches after the weights changed in place (an EMA swap)."""
    with _train_mode(model):
        pass


def learned_state_dict(model: torch.nn.Module) -> dict[str, torch.Tensor]:
    """``model.state_dict()`` without escnn's eval-mode caches (they are rebuilt from the weights)."""
    with _train_mode(model):
        return dict(model.state_dict())


def _is_escnn_cache(model: torch.nn.Module, key: str) -> bool:
    owner, _, attr = key.rpartition(".")
    if attr not in _ESCNN_CACHES:
        return False
    try:
        module = model.get_submodule(owner)
    except AttributeError:
        return False
    from escnn.nn import EquivariantModule  # only reached for keys an escnn model could have written

    return isinstance(module, EquivariantModule)


def load_learned_state(model: torch.nn.Module, state: dict[str, torch.Tensor]) -> None:
    """Strict load of a learned state into ``model``, in whatever mode either was saved or is in.

    Caches written by older checkpoints (saved in eval mode) are skipped; a state without buffers
    (``parameters_only``: a committed run's weights) keeps the model's own, which are constants of the
    architecture (escnn's sampled bases); any other missing or unexpected key raises a RuntimeError, as
    ``load_state_dict(strict=True)`` would."""
    with _train_mode(model):
        result = model.load_state_dict(state, strict=False)
    unexpected = [k for k in result.unexpected_keys if not _is_escnn_cache(model, k)]
    buffers = dict(model.named_buffers(remove_duplicate=False))  # escnn shares one basis between layers
    missing = [k for k in result.missing_keys if k not in buffers]
    if missing or unexpected:
        raise RuntimeError(
            f"Error(s) in loading state_dict for {type(model).__name__}: "
            f"missing keys {missing}, unexpected keys {unexpected}"
        )


def parameters_only(model: torch.nn.Module) -> dict[str, torch.Tensor]:
    """The model's learned parameters without its buffers: for escnn models the buffers are sampled bases
    rebuilt with the architecture (the compact EquiDiff's are 4 of its 9 MB)."""
    return {name: p.detach().clone() for name, p in model.named_parameters()}
