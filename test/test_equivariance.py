"""Equivariance on twin-like scenes: EquiDiff exactly C4 (escnn, exported fp32 and bf16, the shipped
checkpoint), approximately C8, and the baseline measurably not equivariant."""

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from equidiff_core.config import Workspace
from equidiff_core.models import equivariance
from equidiff_core.policy.diffusion import make_policy
from equidiff_core.policy.file import export_policy
from equidiff_core.policy.inference import load_inference_policy
from equidiff_core.policy.normalizer import Normalizer
from equidiff_core.policy.presets import get_preset
from equidiff_core.twin.config import load_twin_config

WS = Workspace()
SCENE = load_twin_config().scene
C4_DEG = (90, 180, 270)
FP32_EXACT = 1e-5  # rot90 permutes voxels and the C4 part of every filter: only float rounding is left
SHIPPED = Path(__file__).resolve().parents[1] / "checkpoints" / "twin_compact" / "policy.pt"


def _policy(name, control="absolute", preset="tiny", seed=0):
    torch.manual_seed(seed)
    policy = make_policy(name, get_preset(preset, control=control), WS)
    policy.set_normalizer(Normalizer.from_workspace(WS))
    return policy.eval()


@pytest.fixture(scope="module")
def scenes():
    return equivariance.twin_scenes(get_preset("tiny"), WS, count=2, seed=1, scene=SCENE)


@pytest.fixture(scope="module")
def equidiff_tiny():
    return _policy("equidiff")


@pytest.fixture(scope="module")
def baseline_tiny():
    return _policy("baseline")


@pytest.fixture(scope="module")
def exported_tiny(equidiff_tiny, tmp_path_factory):
    return export_policy(equidiff_tiny, tmp_path_factory.mktemp("equiv") / "policy.pt")


def test_twin_scenes_hold_the_twins_objects_inside_the_rotation_safe_cylinder(scenes):
    from equidiff_core.twin.config import load_twin_config

    voxels, ee = scenes
    preset = get_preset("tiny")
    assert voxels.shape == (2, 1, 4, 64, 64, 64) and voxels.dtype == torch.uint8 and ee.shape == (2, 1, 10)
    occ = voxels[:, 0, 0].numpy() > 0
    c = (WS.resolution - 1) / 2
    ii, jj = np.meshgrid(np.arange(WS.resolution), np.arange(WS.resolution), indexing="ij")
    radius = equivariance.rotation_safe_radius(preset, WS) / WS.voxel_size
    outside = np.hypot(ii - c, jj - c) > radius + 1
    assert not occ[:, outside].any()
    assert 0.005 < occ.mean() < 0.05  # a table top and two objects, not noise
    cfg = load_twin_config().scene
    for b in range(2):
        rgb = voxels[b, 0, 1:, occ[b]].T.numpy().astype(int)
        for rgba in (cfg.block_rgba, cfg.bowl_rgba, cfg.bowl_mark_rgba, cfg.table_rgba):
            assert (np.abs(rgb - np.asarray(rgba[:3]) * 255).max(1) < 20).any()
        above_table = occ[b, :, :, 4:].sum()  # the block (3 cm) and the bowl's walls (4.1 cm) stand up
        assert above_table > 100
    again, _ = equivariance.twin_scenes(preset, WS, count=2, seed=1, scene=SCENE)
    assert torch.equal(again, voxels)


def test_escnn_denoiser_is_exactly_c4_and_approximately_c8(equidiff_tiny, baseline_tiny, scenes):
    equi = equivariance.denoiser_errors(equivariance.TrainingModel(equidiff_tiny), *scenes)
    base = equivariance.denoiser_errors(equivariance.TrainingModel(baseline_tiny), *scenes)
    assert max(equi[a] for a in C4_DEG) <= FP32_EXACT
    rot45 = [equi[a] for a in (45, 135, 225, 315)]
    assert min(rot45) > 1e-3  # 45 deg is not exact: 3^3 kernels on a cubic grid, resampled voxels ...
    assert max(rot45) < 0.1 * min(base[a] for a in (45, 135, 225, 315))  # ... but far closer than no constraint
    # the baseline is measurably not equivariant: its C4 error is orders of magnitude above EquiDiff's
    assert min(base[a] for a in C4_DEG) > 0.1
    assert min(base[a] for a in C4_DEG) > 1e4 * max(equi[a] for a in C4_DEG)


def test_relative_control_denoiser_is_exactly_c4():
    policy = _policy("equidiff", control="relative", seed=3)
    for angle in (90, -90, 180):
        assert (
            equivariance.noise_predictor_error(policy, math.radians(angle), batch=1, seed=2, scene=SCENE) <= FP32_EXACT
        )


def test_escnn_ddim_sampling_is_exactly_c4_for_equidiff_not_baseline(equidiff_tiny, baseline_tiny, scenes):
    one = (scenes[0][:1], scenes[1][:1])
    equi = equivariance.sampling_errors(equivariance.TrainingModel(equidiff_tiny), *one, C4_DEG, seed=4)
    base = equivariance.sampling_errors(equivariance.TrainingModel(baseline_tiny), *one, (90,), seed=4)
    assert max(equi.values()) <= FP32_EXACT
    assert base[90] > 0.05


def test_exported_fp32_path_is_exactly_c4(exported_tiny, scenes):
    fast = equivariance.ExportedModel(load_inference_policy(exported_tiny, precision="fp32", jit=True))
    report = equivariance.measure(fast, scenes[0][:1], scenes[1][:1], angles_deg=C4_DEG)
    assert report["denoiser"]["c4_max_rel_err"] <= FP32_EXACT
    assert report["sampling"]["c4_max_rel_err"] <= FP32_EXACT


def test_exported_bf16_path_is_c4_to_bf16_precision(exported_tiny, scenes):
    fast = load_inference_policy(exported_tiny, precision="bf16", jit=True)
    assert fast.dtype == torch.bfloat16
    report = equivariance.measure(equivariance.ExportedModel(fast), scenes[0][:1], scenes[1][:1], angles_deg=C4_DEG)
    # bf16 keeps 8 bits of mantissa (relative step 2^-8 = 3.9e-3): a few of those, not an unconstrained network's ~1
    assert report["denoiser"]["c4_max_rel_err"] < 2e-2
    assert report["sampling"]["c4_max_rel_err"] < 2e-2


@pytest.mark.skipif(not SHIPPED.is_file(), reason="the shipped checkpoint is not in this checkout")
def test_shipped_checkpoint_is_exactly_c4_and_beats_a_baseline_at_45_degrees():
    fast = load_inference_policy(SHIPPED, precision="fp32", jit=True)
    voxels, ee = equivariance.twin_scenes(fast.preset, fast.workspace, count=1, seed=7, scene=SCENE)
    report = equivariance.measure(equivariance.ExportedModel(fast), voxels, ee, angles_deg=(45, 90, 180, 270))
    assert report["denoiser"]["c4_max_rel_err"] <= FP32_EXACT
    assert report["sampling"]["c4_max_rel_err"] <= FP32_EXACT
    torch.manual_seed(0)
    baseline = make_policy("baseline", fast.preset, fast.workspace)
    baseline.set_normalizer(fast.normalizer)
    base = equivariance.denoiser_errors(equivariance.TrainingModel(baseline), voxels, ee, (45, 90))
    assert base[90] > 1e4 * report["denoiser"]["c4_max_rel_err"]
    assert report["denoiser"]["rot45_max_rel_err"] < base[45]


@pytest.mark.slow  # ~15 s: every path (bf16 emulated on AVX2 CPUs), 7 rotations, DDIM
def test_check_equivariance_command_prints_one_json_line(capsys):
    from equidiff_ros.cli import main

    assert main(["check", "equivariance", "--preset", "tiny", "--scenes", "1"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 1
    out = json.loads(lines[0])
    assert (out["preset"], out["policy"], out["weights"], out["scenes"]) == ("tiny", "equidiff", "random", 1)
    for path in ("escnn", "exported_fp32"):
        for part in ("denoiser", "sampling"):
            assert out[path][part]["c4_max_rel_err"] <= FP32_EXACT
            assert out[path][part]["rot45_max_rel_err"] > 1e-3
            assert set(out[path][part]["per_element"]) == {f"{45 * k}deg" for k in range(1, 8)}
    assert out["exported_bf16"]["denoiser"]["c4_max_rel_err"] < 2e-2
    assert out["baseline"]["weights"] == "random"
    assert out["baseline"]["denoiser"]["c4_max_rel_err"] > 1e4 * out["escnn"]["denoiser"]["c4_max_rel_err"]
    assert out["cpu"]["cores"] >= 1


def test_check_equivariance_of_the_baseline_has_no_second_baseline(capsys):
    from equidiff_ros.cli import main

    assert main(["check", "equivariance", "--preset", "tiny", "--policy", "baseline", "--scenes", "1"]) == 0
    base = json.loads(capsys.readouterr().out.strip())
    assert base["policy"] == "baseline" and "baseline" not in base
    assert len(base["weights_sha256"]) == 64  # the hash of the weights checked, verified at load
    for path in ("escnn", "exported_fp32", "exported_bf16"):
        assert base[path]["denoiser"]["c4_max_rel_err"] > 0.1


@pytest.mark.slow  # ~15 s: every path (bf16 emulated on AVX2 CPUs), 7 rotations, DDIM
def test_check_equivariance_of_a_training_checkpoint(tmp_path, capsys):
    from equidiff_core.data.synthetic import CubeDataset
    from equidiff_core.training.config import TrainConfig
    from equidiff_core.training.loop import train
    from equidiff_ros.cli import main

    cfg = TrainConfig(
        steps=1,
        batch_size=2,
        warmup_steps=1,
        eval_every=1,
        eval_samples=1,
        val_batches=1,
        checkpoint_every=1,
        log_every=1,
    )
    torch.manual_seed(0)  # train() fits the normaliser to the data
    policy = make_policy("equidiff", get_preset("tiny"), WS)
    result = train(policy, CubeDataset(2, seed=1), CubeDataset(1, seed=2), cfg, tmp_path)
    assert main(["check", "equivariance", "--checkpoint", str(result.checkpoint), "--scenes", "1"]) == 0
    out = json.loads(capsys.readouterr().out.strip())
    assert out["weights"] == str(result.checkpoint) and out["preset"] == "tiny"
    assert out["escnn"]["denoiser"]["c4_max_rel_err"] <= FP32_EXACT
    assert out["exported_fp32"]["sampling"]["c4_max_rel_err"] <= FP32_EXACT
    assert out["baseline"]["denoiser"]["c4_max_rel_err"] > 0.1


def test_check_equivariance_rejects_a_bad_checkpoint(tmp_path, capsys):
    from equidiff_ros.cli import main

    bad = tmp_path / "policy.pt"
    bad.write_bytes(b"not a checkpoint")
    assert main(["check", "equivariance", "--checkpoint", str(bad)]) == 2
    assert str(bad) in capsys.readouterr().err
    assert main(["check", "equivariance", "--checkpoint", str(tmp_path / "missing.pt")]) == 2
    assert "missing.pt" in capsys.readouterr().err
