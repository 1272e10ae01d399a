"""Exported inference policies: plain torch, equal outputs, clear checkpoint errors."""

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import torch

from equidiff_core.config import Workspace
from equidiff_core.models.equivariance import random_observation, twin_scenes
from equidiff_core.policy.diffusion import PolicyInputError, make_policy
from equidiff_core.policy.file import CheckpointError, export_policy, read_policy_file
from equidiff_core.policy.inference import load_inference_policy
from equidiff_core.policy.normalizer import Normalizer
from equidiff_core.policy.presets import get_preset
from equidiff_core.twin.config import load_twin_config

WS = Workspace()
# The twin checkpoint shipped until the official encoder layout was trained (legacy layout)
LEGACY = Path(__file__).resolve().parents[1] / "checkpoints" / "twin_compact_legacy" / "policy.pt"
# Its DDIM-16 actions (steps 0, 7, 15) on twin scene seed 7 with seed 0, fp32, computed at 9845433,
# before the official encoder layout: old files must predict exactly as before.
LEGACY_ACTIONS = [
    [
        0.39222419,
        -0.02841101,
        0.15675224,
        -0.17525984,
        1.0,
        -0.0103813,
        0.98565179,
        0.11630499,
        -0.02536722,
        0.00875571,
    ],
    [
        0.3914265,
        -0.07525568,
        0.10228261,
        -0.17707609,
        0.92764175,
        0.03025702,
        0.66820025,
        0.17877193,
        0.08309109,
        0.08328987,
    ],
    [
        0.38804916,
        -0.07696071,
        0.04551379,
        -0.2022438,
        0.93422771,
        0.04871403,
        0.60888714,
        0.18283252,
        0.08818103,
        0.09174807,
    ],
]


def _policy(name, preset="tiny", control="absolute"):
    torch.manual_seed(0)
    p = make_policy(name, get_preset(preset, control=control), WS)
    p.set_normalizer(Normalizer.from_workspace(WS))
    return p.eval()


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    policy = _policy("equidiff")
    path = export_policy(policy, tmp_path_factory.mktemp("export") / "policy.pt")
    return policy, path


@torch.no_grad()
def _max_abs_diff_noise_predictor(policy, plain):
    vox, ee = random_observation(policy, batch=2, seed=3, fill=0.05)
    v, e = policy.prepare_input(vox, ee, "center")
    x = torch.randn(2, 16, policy.codec.dim, generator=torch.Generator().manual_seed(0))
    t = torch.tensor([3, 70])
    ref = policy.model(x, t, v, e)
    return float((plain(x, t, v, e) - ref).abs().max() / ref.abs().max())


@pytest.mark.parametrize("preset", ["tiny", "compact"])
def test_export_matches_escnn_model(preset):
    policy = _policy("equidiff", preset)
    assert _max_abs_diff_noise_predictor(policy, policy.model.export_plain()) < 1e-5


def test_exported_policy_predicts_like_the_training_policy(exported):
    policy, path = exported
    inf = load_inference_policy(path)
    assert inf.preset == policy.preset and inf.workspace == WS and inf.normalizer == policy.normalizer
    vox, ee = random_observation(policy, batch=1, seed=5)
    a = inf.predict(vox[0, 0].numpy(), ee[0, 0].numpy(), seed=7)
    assert a.shape == (16, 10) and np.isfinite(a).all()
    noise = torch.randn(1, 16, 10, generator=torch.Generator().manual_seed(7))
    ref = policy.predict_action({"voxels": vox, "ee": ee}, noise=noise)["action_pred"][0].numpy()
    np.testing.assert_allclose(a, ref, atol=1e-5)
    np.testing.assert_array_equal(a, inf.predict(vox[0, 0].numpy(), ee[0, 0].numpy(), seed=7))  # seeded = repeatable
    # the fast path (bf16, channels_last, jit.trace) stays close to fp32
    fast = load_inference_policy(path, precision="bf16", jit=True)
    assert fast.matmul_convs > 0  # the U-Net's Conv1d run as GEMMs in bf16 on CPU
    b = fast.predict(vox[0, 0].numpy(), ee[0, 0].numpy(), seed=7)
    assert np.abs(b - a)[:, :3].max() < 0.05


@pytest.mark.skipif(not LEGACY.is_file(), reason="the legacy checkpoint is not in this checkout")
def test_legacy_checkpoint_keeps_its_legacy_encoder_and_predicts_as_before():
    inf = load_inference_policy(LEGACY)
    assert inf.preset.encoder_layout == "legacy"  # saved before the field existed
    vox, ee = twin_scenes(inf.preset, inf.workspace, count=1, seed=7, scene=load_twin_config().scene)
    a = inf.predict(vox[0, 0].numpy(), ee[0, 0].numpy(), seed=0)
    np.testing.assert_allclose(a[[0, 7, 15]], LEGACY_ACTIONS, atol=1e-5)
    sixteen = load_inference_policy(LEGACY, inference_steps=16, timestep_spacing="leading")
    np.testing.assert_array_equal(a, sixteen.predict(vox[0, 0].numpy(), ee[0, 0].numpy(), seed=0))


@pytest.mark.slow
def test_compiled_denoising_step_predicts_like_the_traced_one(exported):
    """torch.compile (an optional switch): same actions as the traced bf16 policy."""
    policy, path = exported
    vox, ee = random_observation(policy, batch=1, seed=5, fill=0.05)
    vox, ee = vox[0, 0].numpy(), ee[0, 0].numpy()
    reference = load_inference_policy(path, precision="fp32").predict(vox, ee, seed=3)
    traced = load_inference_policy(path, precision="bf16", jit=True)
    compiled = load_inference_policy(path, precision="bf16", jit=True, compile=True)
    assert compiled.compiled and not traced.compiled
    a, b = traced.predict(vox, ee, seed=3), compiled.predict(vox, ee, seed=3)
    # bf16 rounding in another kernel order (random weights amplify it), not another model
    assert np.abs(b - a)[:, :3].max() < 0.03 and np.abs(b - reference)[:, :3].max() < 0.05


def test_a_failed_compile_warns_and_keeps_the_traced_step(exported, monkeypatch):
    def broken_compile(fn, **_):
        def run(*args):
            raise RuntimeError("InductorError: no working C++ compiler found\nmore detail")

        return run

    monkeypatch.setattr(torch, "compile", broken_compile)
    _, path = exported
    with pytest.warns(RuntimeWarning, match="torch.compile of the denoising step failed.*no working C"):
        policy = load_inference_policy(path, precision="bf16", jit=True, compile=True)
    assert not policy.compiled and policy.jit
    assert policy.predict(*policy._blank_observation(), seed=0).shape == (policy.preset.horizon, 10)


@pytest.mark.parametrize("precision, jit", [("fp32", False), ("bf16", True)])
def test_the_sampling_a_cuda_graph_captures_predicts_exactly_like_the_plain_path(exported, precision, jit):
    """The CUDA-graph path samples on fixed buffers with its own loop; run eagerly on the
    CPU it must give the plain path's actions to the bit, plain and RTC-guided (on CUDA the
    graph replays exactly this code; the GPU check records the difference there)."""
    policy, path = exported
    vox, ee = random_observation(policy, batch=1, seed=5, fill=0.05)
    vox, ee = vox[0, 0].numpy(), ee[0, 0].numpy()
    plain = load_inference_policy(path, precision=precision, jit=jit)
    static = load_inference_policy(path, precision=precision, jit=jit)
    static._use_static_buffers(capture=False)
    a = plain.predict(vox, ee, seed=3)
    np.testing.assert_array_equal(static.predict(vox, ee, seed=3), a)
    # another observation, noise and a guide: the buffers are refilled per call, not replayed stale
    vox2, ee2 = np.roll(vox, 3, axis=1), ee + np.float32(0.01) * (np.arange(10) < 3)
    guide = (a + 0.02, np.linspace(1.0, 0.0, policy.preset.horizon))
    guided = plain.predict(vox2, ee2, seed=4, guide=guide)
    np.testing.assert_array_equal(static.predict(vox2, ee2, seed=4, guide=guide), guided)
    with pytest.raises(PolicyInputError, match="noise"):
        static.predict(vox, ee, noise=np.zeros((8, 10), np.float32))


def test_cuda_graph_asks_for_a_cuda_device(exported, capsys):
    from equidiff_ros.cli import main

    with pytest.raises(ValueError, match="cuda_graph needs a CUDA device"):
        load_inference_policy(exported[1], device="cpu", cuda_graph=True)
    assert main(["bench", "policy", "--preset", "tiny", "--device", "cpu", "--graph"]) == 2
    assert "--graph needs --device cuda" in capsys.readouterr().err


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA graphs need a GPU")
def test_cuda_graph_replays_the_traced_policys_actions(exported):
    policy, path = exported
    vox, ee = random_observation(policy, batch=1, seed=5, fill=0.05)
    vox, ee = vox[0, 0].numpy(), ee[0, 0].numpy()
    traced = load_inference_policy(path, device="cuda", precision="bf16", jit=True)
    graphed = load_inference_policy(path, device="cuda", precision="bf16", jit=True, cuda_graph=True)
    assert graphed.graphed and not traced.graphed
    a, b = traced.predict(vox, ee, seed=3), graphed.predict(vox, ee, seed=3)
    assert np.abs(b - a)[:, :3].max() < 0.03  # the same kernels; at most another bf16 rounding (cuBLAS workspace)
    other = vox.copy()
    other[:, ::2] = 0  # new inputs reach the graph: its buffers are refilled, not replayed stale
    assert np.abs(graphed.predict(other, ee, seed=3) - traced.predict(other, ee, seed=3))[:, :3].max() < 0.03


@pytest.mark.parametrize("kernel, stride, padding, bias", [(5, 1, 2, True), (3, 2, 1, True), (1, 1, 0, False)])
def test_matmul_conv1d_equals_conv1d(kernel, stride, padding, bias):
    from equidiff_core.models.cpu_kernels import MatmulConv1d

    torch.manual_seed(0)
    conv = torch.nn.Conv1d(12, 20, kernel, stride, padding, bias=bias)
    x = torch.randn(3, 12, 16)
    torch.testing.assert_close(MatmulConv1d(conv)(x), conv(x), rtol=1e-5, atol=1e-5)
    with pytest.raises(ValueError, match="plain convolutions"):
        MatmulConv1d(torch.nn.Conv1d(12, 20, 3, groups=4))


@pytest.mark.parametrize("channels, steps, bias", [(12, 4, True), (7, 5, False), (16, 1, True)])
def test_matmul_conv_transpose1d_equals_conv_transpose1d(channels, steps, bias):
    from equidiff_core.models.cpu_kernels import MatmulConvTranspose1d

    torch.manual_seed(0)
    conv = torch.nn.ConvTranspose1d(channels, channels + 3, 4, 2, 1, bias=bias)  # the U-Net's upsampler
    x = torch.randn(3, channels, steps)
    torch.testing.assert_close(MatmulConvTranspose1d(conv)(x), conv(x), rtol=1e-5, atol=1e-5)
    with pytest.raises(ValueError, match="kernel = 2"):
        MatmulConvTranspose1d(torch.nn.ConvTranspose1d(4, 4, 3, 2, 1))


def test_fast_mish_equals_mish():
    from equidiff_core.models.cpu_kernels import FastMish

    x = torch.cat([torch.linspace(-60.0, 60.0, 20001), torch.tensor([-1e4, 1e4, 0.0])])
    torch.testing.assert_close(FastMish()(x), torch.nn.functional.mish(x), rtol=1e-5, atol=1e-6)


def test_baseline_and_relative_export(tmp_path):
    for name, control in (("baseline", "absolute"), ("equidiff", "relative")):
        policy = _policy(name, control=control)
        path = export_policy(policy, tmp_path / f"{name}_{control}.pt")
        vox, ee = random_observation(policy, batch=1, seed=2)
        noise = torch.randn(1, 16, policy.codec.dim, generator=torch.Generator().manual_seed(1))
        ref = policy.predict_action({"voxels": vox, "ee": ee}, noise=noise)["action_pred"][0].numpy()
        got = load_inference_policy(path).predict(vox[0, 0].numpy(), ee[0, 0].numpy(), seed=1)
        np.testing.assert_allclose(got, ref, atol=1e-5)


def test_policy_file_loads_with_weights_only_and_json_config(exported):
    _, path = exported
    payload = torch.load(path, weights_only=True)
    config = json.loads(payload["config_json"])
    assert config["policy"] == "equidiff" and config["preset"]["name"] == "tiny"
    assert all(isinstance(v, torch.Tensor) for v in payload["state_dict"].values())


def test_inference_does_not_import_escnn(exported):
    _, path = exported
    code = textwrap.dedent(f"""
        import sys, numpy as np
        from equidiff_core.policy.inference import load_inference_policy
        p = load_inference_policy({str(path)!r})
        vox = np.zeros((4, 64, 64, 64), np.uint8); ee = np.array([0.45, 0, 0.2, 1, 0, 0, 0, 1, 0, 0.04], np.float32)
        a = p.predict(vox, ee, seed=0)
        assert a.shape == (16, 10)
        bad = sorted(m for m in sys.modules if m.split('.')[0] in ('escnn', 'lie_learn', 'rclpy'))
        print('LOADED', bad)
        """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert "LOADED []" in out.stdout


def test_missing_corrupt_and_incompatible_files(exported, tmp_path):
    _, path = exported
    with pytest.raises(CheckpointError, match="no such"):
        load_inference_policy(tmp_path / "nope.pt")
    corrupt = tmp_path / "corrupt.pt"
    corrupt.write_bytes(path.read_bytes()[:1000])
    with pytest.raises(CheckpointError, match="not a readable"):
        load_inference_policy(corrupt)
    other = tmp_path / "other.pt"
    torch.save({"weights": torch.zeros(3)}, other)
    with pytest.raises(CheckpointError, match="not an exported"):
        load_inference_policy(other)
    payload = torch.load(path, weights_only=True)
    wrong = tmp_path / "wrong_preset.pt"
    cfg = json.loads(payload["config_json"])
    cfg["preset"] = get_preset("compact").to_dict()
    torch.save({**payload, "config_json": json.dumps(cfg)}, wrong)
    with pytest.raises(CheckpointError, match="do not fit"):
        load_inference_policy(wrong)
    future = tmp_path / "future.pt"
    torch.save({**payload, "version": 99}, future)
    with pytest.raises(CheckpointError, match="version"):
        read_policy_file(future)
    bad_cfg = tmp_path / "bad_cfg.pt"
    cfg = json.loads(payload["config_json"])
    cfg["preset"]["horizon"] = "sixteen"
    torch.save({**payload, "config_json": json.dumps(cfg)}, bad_cfg)
    with pytest.raises(CheckpointError, match="incompatible"):
        load_inference_policy(bad_cfg)


def test_bad_observations_raise(exported):
    _, path = exported
    inf = load_inference_policy(path)
    ee = np.array([0.45, 0, 0.2, 1, 0, 0, 0, 1, 0, 0.04], np.float32)
    vox = np.zeros((4, 64, 64, 64), np.uint8)
    with pytest.raises(PolicyInputError, match="uint8"):
        inf.predict(vox.astype(np.float32), ee)
    for size in (32, 58, 80):  # any grid but the workspace's (64^3) would be cropped from another part of space
        with pytest.raises(PolicyInputError, match="not this policy's workspace grid"):
            inf.predict(np.zeros((4, size, size, size), np.uint8), ee)
    with pytest.raises(PolicyInputError, match="NaN"):
        inf.predict(vox, np.full(10, np.nan, np.float32))
    with pytest.raises(PolicyInputError, match=r"\(10,\)"):
        inf.predict(vox, ee[:9])


def test_bench_policy_command_prints_one_json_line(capsys):
    from equidiff_ros.cli import main

    args = ["bench", "policy", "--preset", "tiny", "--iters", "3", "--eager-iters", "1", "--doubt-samples", "2"]
    assert main(args) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 1
    out = json.loads(lines[0])
    for key in (
        "preset",
        "params",
        "encoder_ms",
        "step_ms",
        "ddim16_median_ms",
        "ddim16_p99_ms",
        "eager_ddim16_median_ms",
        "device",
    ):
        assert key in out
    assert out["preset"] == "tiny" and out["params"] > 0
    assert 0 < out["encoder_ms"] < out["ddim16_median_ms"] <= out["ddim16_p99_ms"]
    # the default doubt signal's cost beside DDIM-16 timed in the same rounds, and K = 2 samples'
    assert out["doubt_signal"] in ("disagreement", "spread") and out["doubt_ms"] >= 0
    assert out["doubt_vs_ddim16_percent"] == pytest.approx(
        100 * out["doubt_ms"] / out["doubt_ddim16_median_ms"], abs=0.1
    )
    assert list(out["spread_extra_ms"]) == ["2"] and "2" in out["spread_vs_ddim16_percent"]
    assert main([*args[:-1], "1"]) == 2  # one sample has no spread


def test_bench_policy_times_several_modes_and_rtc_in_one_run(capsys):
    from equidiff_ros.cli import main

    modes = "fp32-eager,bf16-traced-graph,bf16-traced"
    args = ["bench", "policy", "--preset", "tiny", "--iters", "2", "--eager-iters", "0", "--rtc", "--modes", modes]
    assert main(args) == 0
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert list(out["modes"]) == modes.split(",")
    eager, graph, traced = (out["modes"][m] for m in modes.split(","))
    assert graph == {"skipped": "CUDA graphs need a CUDA device"}  # on this CPU; the GPU check runs it
    assert (eager["precision"], eager["jit"], traced["precision"], traced["jit"]) == ("fp32", False, "bf16", True)
    for mode in (eager, traced):
        assert mode["ddim16_median_ms"] <= mode["ddim16_p99_ms"] and mode["rtc_median_ms"] > 0
        assert mode["rtc_vs_plain"] == pytest.approx(mode["rtc_median_ms"] / mode["ddim16_median_ms"], rel=0.01)
    assert out["mode"] == "fp32-eager" and out["ddim16_median_ms"] == eager["ddim16_median_ms"]
    assert out["best_mode"] in ("fp32-eager", "bf16-traced")
    assert out["best_ddim16_p99_ms"] == min(eager["ddim16_p99_ms"], traced["ddim16_p99_ms"])
    assert main([*args[:-1], "fp32-warp"]) == 2
    assert "PRECISION-EXECUTION" in capsys.readouterr().err


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the message of a machine without CUDA")
def test_cuda_without_cuda_is_a_clear_error_not_a_traceback(exported, capsys):
    from equidiff_ros.cli import main

    assert main(["bench", "policy", "--preset", "tiny", "--device", "cuda"]) == 2
    assert "CUDA is not available" in capsys.readouterr().err
    with pytest.raises(ValueError, match="CUDA is not available"):
        load_inference_policy(exported[1], device="cuda")


def test_precision_choices(exported):
    _, path = exported
    auto = load_inference_policy(path, precision="auto")
    assert auto.precision == "fp32"  # on a CPU, with or without native bf16
    with pytest.raises(ValueError, match="precision"):
        load_inference_policy(path, precision="fp8")


def test_policy_files_carry_a_weights_hash_checked_at_load(exported, tmp_path):
    """export_policy stores the sha256 of the weights; a changed weight is refused by name; a file
    without a hash (written before) loads and is reported unhashed; rewrite_with_hash adds it, bit for bit."""
    from equidiff_core.policy.file import UNHASHED, open_policy_file, rewrite_with_hash, weights_sha256

    _, path = exported
    payload = torch.load(path, weights_only=True)
    stored = payload["weights_sha256"]
    assert len(stored) == 64 and stored == weights_sha256(payload["state_dict"])
    assert load_inference_policy(path).weights_sha256 == stored
    # the hash does not depend on the dict's order, only on names, dtypes, shapes and bytes
    assert weights_sha256(dict(reversed(list(payload["state_dict"].items())))) == stored
    altered = {k: v.clone() for k, v in payload["state_dict"].items()}
    name = next(k for k, v in altered.items() if v.is_floating_point() and v.numel() > 1)
    flat = altered[name].view(-1)
    flat.view(torch.int32)[0] ^= 1  # one flipped bit in one weight
    flipped = tmp_path / "flipped.pt"
    torch.save({**payload, "state_dict": altered}, flipped)
    with pytest.raises(CheckpointError, match="do not match their stored sha256"):
        load_inference_policy(flipped)
    old = tmp_path / "old.pt"
    torch.save({k: v for k, v in payload.items() if k != "weights_sha256"}, old)
    assert open_policy_file(old).weights_sha256 is None
    assert load_inference_policy(old).weights_sha256 == UNHASHED
    assert rewrite_with_hash(old) == stored
    again = open_policy_file(old)
    assert again.weights_sha256 == stored
    for k, v in payload["state_dict"].items():
        assert torch.equal(again.state[k], v)


def test_checkpoint_errors_name_the_real_reason(exported, tmp_path, capsys):
    """Each failure says what it is; a future policy file is not reported as "not a training checkpoint"."""
    from equidiff_ros.cli import main

    _, path = exported
    payload = torch.load(path, weights_only=True)
    future = tmp_path / "future.pt"
    torch.save({**payload, "version": 99}, future)
    with pytest.raises(CheckpointError, match=r"version 99, which this equidiff cannot read \(it reads version 1"):
        load_inference_policy(future)
    cut = tmp_path / "cut.pt"
    cut.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    with pytest.raises(CheckpointError, match="truncated"):
        load_inference_policy(cut)
    ckpt_like = tmp_path / "ckpt_like.pt"
    torch.save({"format": "equidiff_train_ckpt", "version": 1}, ckpt_like)
    with pytest.raises(CheckpointError, match="it is an equidiff training checkpoint"):
        load_inference_policy(ckpt_like)
    # equidiff check equivariance falls back to the training-checkpoint loader only for another format
    assert main(["check", "equivariance", "--checkpoint", str(future), "--scenes", "1"]) == 2
    err = capsys.readouterr().err
    assert "version 99" in err and "training checkpoint" not in err


def test_shipped_policy_files_and_checkpoints_carry_a_checked_weights_hash():
    """Re-written by scripts/rewrite_integrity.py; load_checked verifies each hash."""
    from equidiff_core.policy.file import FORMAT, HASH_KEY, VERSION, load_checked
    from equidiff_core.training.loop import load_training_checkpoint

    root = Path(__file__).resolve().parents[1] / "checkpoints"
    policies, ckpts = sorted(root.rglob("policy.pt")), sorted(root.rglob("*.ckpt"))
    assert policies and ckpts
    for path in policies:
        assert load_checked(path, FORMAT, VERSION, "policy file", "a policy", "state_dict").get(HASH_KEY), path
    for path in ckpts:
        assert load_training_checkpoint(path).get(HASH_KEY), path


SHIPPED = Path(__file__).resolve().parents[1] / "checkpoints" / "twin_compact" / "policy.pt"


def _encoder_test_grids(preset, workspace) -> list[np.ndarray]:
    """uint8 grids (4, R, R, R): two twin-like scenes, random sparse voxels, an empty grid, every voxel
    occupied, and only the crop's outer shell occupied (where the convolutions' zero padding acts)."""
    R, S = workspace.resolution, preset.crop
    rng = np.random.default_rng(0)
    scenes, _ = twin_scenes(preset, workspace, count=2, seed=3, scene=load_twin_config().scene)
    grids = [g.numpy() for g in scenes[:, 0]]
    grids.append(
        random_observation(type("P", (), {"preset": preset, "workspace": workspace}), 1, seed=2)[0][0, 0].numpy()
    )
    grids.append(np.zeros((4, R, R, R), np.uint8))
    full = rng.integers(1, 256, (4, R, R, R), dtype=np.uint8)
    full[0] = 255
    grids.append(full)
    lo = (R - S) // 2
    shell = full.copy()
    shell[:, lo + 1 : lo + S - 1, lo + 1 : lo + S - 1, lo + 1 : lo + S - 1] = 0
    grids.append(shell)
    return grids


@pytest.mark.parametrize("which", ["tiny", "shipped"])
def test_the_onednn_encoder_computes_what_the_native_one_did(exported, which):
    if which == "shipped" and not SHIPPED.is_file():
        pytest.skip("the shipped checkpoint is not in this checkout")
    path = exported[1] if which == "tiny" else SHIPPED
    # the shipped file as deployed (traced; the exported-policy equivariance tests trace the tiny one)
    fast = load_inference_policy(path, precision="fp32", jit=which == "shipped")
    old = load_inference_policy(path, precision="fp32", encoder_kernels="native")
    assert fast.onednn_convs == 8 and fast.channels_last and fast.pad_channels == 0  # the default on a CPU
    assert {type(m).__name__ for m in fast.net.encoder} >= {"OneDnnConv3d", "WholeMapConv3d"}
    assert old.onednn_convs == 0 and not old.channels_last and old.pad_channels == 4  # the path before
    ee = np.zeros(10, np.float32)
    ee[:3], ee[3], ee[7] = fast.workspace.center, 1.0, 1.0
    grids = _encoder_test_grids(fast.preset, fast.workspace)
    for grid in grids:
        ref = old.encode(grid, ee)
        assert float((fast.encode(grid, ee) - ref).abs().max()) <= 1e-5 * float(ref.abs().max())
    np.testing.assert_allclose(fast.predict(grids[0], ee, seed=3), old.predict(grids[0], ee, seed=3), atol=1e-5)


def test_encoder_kernels_must_be_known(exported):
    with pytest.raises(ValueError, match="encoder_kernels"):
        load_inference_policy(exported[1], encoder_kernels="fastest")


def test_inference_steps_are_an_inference_time_setting(exported, tmp_path):
    """The preset's 16 steps predict exactly as without the setting; fewer steps (either spacing) still
    give valid chunks; a policy file's own ``sampler`` entry sets them, the arguments override it."""
    policy, path = exported
    vox, ee = random_observation(policy, batch=1, seed=5)
    obs = (vox[0, 0].numpy(), ee[0, 0].numpy())
    default = load_inference_policy(path)
    assert default.inference_steps == 16 and default.timestep_spacing == "leading"
    a = default.predict(*obs, seed=7)
    np.testing.assert_array_equal(a, load_inference_policy(path, inference_steps=16).predict(*obs, seed=7))
    for spacing in ("leading", "trailing"):
        for k in (8, 4, 2, 1):
            few = load_inference_policy(path, inference_steps=k, timestep_spacing=spacing)
            assert few.inference_steps == k == len(few.scheduler.timesteps)
            b = few.predict(*obs, seed=7)
            assert b.shape == (16, 10) and np.isfinite(b).all()
            assert not np.array_equal(a, b)
    assert [
        int(t) for t in load_inference_policy(path, inference_steps=1, timestep_spacing="trailing").scheduler.timesteps
    ] == [99]
    with pytest.raises(ValueError, match="inference steps"):
        load_inference_policy(path, inference_steps=0)
    with pytest.raises(ValueError, match="spacing"):
        load_inference_policy(path, timestep_spacing="linspace-ish")
    payload = torch.load(path, weights_only=True)
    config = json.loads(payload["config_json"])
    student = tmp_path / "student.pt"
    torch.save({**payload, "config_json": json.dumps({**config, "sampler": {"steps": 2}})}, student)
    assert load_inference_policy(student).inference_steps == 2
    assert load_inference_policy(student, inference_steps=4).inference_steps == 4
    torch.save({**payload, "config_json": json.dumps({**config, "sampler": {"steps": 500}})}, student)
    with pytest.raises(CheckpointError, match="inference steps"):
        load_inference_policy(student)
