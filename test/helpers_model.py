"""Model-test helpers (the synthetic cube data lives in ``equidiff_core.data.synthetic``)."""

from __future__ import annotations

from equidiff_core.config import Workspace


def export_tiny_baseline(path):
    """An untrained export of the baseline at the tiny preset: loads and predicts in a fraction of
    a second, and a node treats every exported policy alike."""
    from equidiff_core.policy.diffusion import make_policy
    from equidiff_core.policy.file import export_policy
    from equidiff_core.policy.normalizer import Normalizer
    from equidiff_core.policy.presets import get_preset

    ws = Workspace()
    policy = make_policy("baseline", get_preset("tiny"), ws)
    policy.set_normalizer(Normalizer.from_workspace(ws))
    return export_policy(policy, path)
