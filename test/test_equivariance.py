"""Equivariance of EquiDiff (issue 4, item 6), measured against the baseline."""

import math

import pytest
import torch

from equidiff_core.config import Workspace
from equidiff_core.models import equivariance
from equidiff_core.normalizer import Normalizer
from equidiff_core.policies import make_policy
from equidiff_core.presets import get_preset

WS = Workspace()
C4 = [math.pi / 2 * k for k in (1, 2, 3)]


def _policy(name, control="absolute", preset="tiny", seed=0):
    torch.manual_seed(seed)
    policy = make_policy(name, get_preset(preset, control=control), WS)
    policy.set_normalizer(Normalizer.from_workspace(WS))
    return policy.eval()


@pytest.fixture(scope="module")
def equidiff_abs():
    return _policy("equidiff")


@pytest.fixture(scope="module")
def baseline_abs():
    return _policy("baseline")


@pytest.mark.parametrize("theta", C4)
def test_noise_predictor_is_c4_equivariant(equidiff_abs, theta):
    assert equivariance.noise_predictor_error(equidiff_abs, theta, batch=2, seed=1) < 1e-4


def test_noise_predictor_relative_control_is_c4_equivariant():
    policy = _policy("equidiff", control="relative", seed=3)
    for theta in C4:
        assert equivariance.noise_predictor_error(policy, theta, batch=1, seed=2) < 1e-4


def test_odd_c8_elements_are_approximate_but_bounded(equidiff_abs):
    err = equivariance.noise_predictor_error(equidiff_abs, math.pi / 4, batch=1, seed=1)
    assert err > 1e-6  # voxel resampling at 45 deg is not a permutation: not exact ...
    assert err < 1.0  # ... but a (much) smaller error than an unconstrained network's


@pytest.mark.parametrize("theta", [math.pi / 2, math.pi])
def test_baseline_is_not_equivariant(baseline_abs, theta):
    assert equivariance.noise_predictor_error(baseline_abs, theta, batch=2, seed=1) > 1e-2


def test_ddim_sampling_is_equivariant_for_equidiff_not_baseline(equidiff_abs, baseline_abs):
    theta = math.pi / 2
    assert equivariance.sampling_error(equidiff_abs, theta, batch=1, seed=4) < 1e-4
    assert equivariance.sampling_error(baseline_abs, theta, batch=1, seed=4) > 1e-2


def test_ddim_sampling_relative_control_is_equivariant():
    policy = _policy("equidiff", control="relative", seed=5)
    assert equivariance.sampling_error(policy, -math.pi / 2, batch=1, seed=6) < 1e-4


def test_group_report_keys(equidiff_abs):
    report = equivariance.group_report(equidiff_abs, batch=1)
    assert set(report) >= {"c4_max_rel_err", "c8_max_rel_err"}
    assert report["c4_max_rel_err"] < 1e-4 <= report["c8_max_rel_err"]
    assert len(report["per_element"]) == 7


def test_check_equivariance_command_prints_one_json_line(capsys):
    import json

    from equidiff_ros.cli import main

    assert main(["check", "equivariance", "--preset", "tiny", "--policy", "equidiff", "--batch", "1"]) == 0
    equi = json.loads(capsys.readouterr().out.strip())
    assert equi["c4_max_rel_err"] < 1e-4 and equi["c8_max_rel_err"] < 1.0
    assert main(["check", "equivariance", "--preset", "tiny", "--policy", "baseline", "--batch", "1"]) == 0
    base = json.loads(capsys.readouterr().out.strip())
    assert base["c4_max_rel_err"] > 100 * equi["c4_max_rel_err"]
