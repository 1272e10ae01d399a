"""Training loop: overfitting, resume, EMA with escnn, callbacks, checkpoints."""

import contextlib
import dataclasses
import json

import numpy as np
import pytest
import torch

from equidiff_core.config import ConfigError, Workspace, from_dict
from equidiff_core.data.synthetic import CubeDataset
from equidiff_core.policy.diffusion import make_policy
from equidiff_core.policy.file import CheckpointError
from equidiff_core.policy.inference import load_inference_policy
from equidiff_core.policy.presets import get_preset
from equidiff_core.training.config import TrainConfig, TrainingError, resolve_device
from equidiff_core.training.loop import (
    load_policy_from_checkpoint,
    load_training_checkpoint,
    previous_optimizer_step,
    train,
    without_optimizer_state,
)

WS = Workspace()


class Recorder:
    def __init__(self):
        self.steps, self.evals, self.ended = [], [], None

    def on_step(self, step, metrics):
        self.steps.append((step, metrics))

    def on_eval(self, step, metrics, samples):
        self.evals.append((step, metrics, samples))

    def on_end(self, result):
        self.ended = result


def _quick_cfg(**kw):
    base = {
        "steps": 2,
        "batch_size": 2,
        "warmup_steps": 1,
        "eval_every": 2,
        "eval_samples": 1,
        "val_batches": 1,
        "checkpoint_every": 1,
        "log_every": 1,
    }
    return TrainConfig(**{**base, **kw})


def test_train_resume_callbacks_and_files(tmp_path):
    ds = CubeDataset(3, seed=1)
    rec = Recorder()
    policy = make_policy("equidiff", get_preset("tiny"), WS)
    result = train(policy, ds, CubeDataset(2, seed=2), _quick_cfg(ema=True), tmp_path, [rec])
    assert [s for s, _ in rec.steps] == [1, 2] and rec.ended is result
    ((step, metrics, samples),) = rec.evals
    assert step == 2 and np.isfinite(metrics["val_loss"])
    assert (
        samples[0]["pred"].shape == (16, 10) and samples[0]["gt"].shape == (16, 10) and samples[0]["ee"].shape == (10,)
    )
    assert result.checkpoint == tmp_path / "last.ckpt" and result.exported == tmp_path / "policy.pt"
    assert json.loads((tmp_path / "history.json").read_text())[-1]["step"] == 2
    state = load_training_checkpoint(result.checkpoint)  # weights_only=True inside
    assert state["step"] == 2 and state["ema"] is not None
    assert load_inference_policy(result.exported).predict(
        ds[0]["voxels"][0].numpy(), ds[0]["ee"][0].numpy(), seed=0
    ).shape == (16, 10)

    # resume: a fresh policy object continues at step 3 from last.ckpt
    rec2 = Recorder()
    again = make_policy("equidiff", get_preset("tiny"), WS)
    train(again, ds, None, _quick_cfg(steps=3, ema=True), tmp_path, [rec2])
    assert [s for s, _ in rec2.steps] == [3]
    assert again.normalizer == policy.normalizer
    restored = load_policy_from_checkpoint(tmp_path / "last.ckpt", ema=False)  # the weights training goes on from
    for a, b in zip(restored.model.parameters(), again.model.parameters()):
        torch.testing.assert_close(a, b)

    # resuming into a different preset is refused rather than silently mixed
    with pytest.raises(TrainingError, match="different policy/preset"):
        train(make_policy("baseline", get_preset("tiny"), WS), ds, None, _quick_cfg(steps=4), tmp_path)


def test_every_step_trains_in_train_mode_without_resetting_it_each_step(tmp_path, monkeypatch):
    """Each step's loss is computed in train mode, also right after an evaluation put the model in eval
    mode; the mode is set again only then (escnn's ``train()`` hashes every basis expansion: a tenth of
    a tiny step when it ran before every step)."""
    ds = CubeDataset(3, seed=1)
    torch.manual_seed(0)
    policy = make_policy("equidiff", get_preset("tiny"), WS)
    modes, calls = [], []
    compute_loss, set_mode = policy.compute_loss, policy.train

    def record_mode(*args, **kwargs):
        if torch.is_grad_enabled():  # a training step, not the evaluation's validation loss
            modes.append(policy.training)
        return compute_loss(*args, **kwargs)

    monkeypatch.setattr(policy, "compute_loss", record_mode)
    monkeypatch.setattr(policy, "train", lambda mode=True: calls.append(mode) or set_mode(mode))
    policy.eval()
    train(policy, ds, ds, _quick_cfg(steps=6, eval_every=2, checkpoint_every=0), tmp_path)
    assert modes == [True] * 6
    assert calls.count(True) == 3  # at the start, after the evaluations at steps 2 and 4 (6 is the last)


def test_the_fused_optimiser_trains_the_weights_the_per_tensor_loop_trains(tmp_path):
    """AdamW's fused kernel, the gradient clip over the parameter list taken once, gives the same weights as the
    step before (AdamW's loop over every tensor, the clip walking the model each step), to fp32 rounding; the
    checkpoint records the kernel, which a resumed run keeps."""
    ds = CubeDataset(3, seed=1)
    cfg = _quick_cfg(steps=3, eval_every=0, checkpoint_every=3, lr=1e-3, warmup_steps=0, grad_clip=0.5)
    weights = {}
    for name in ("fused", "loop"):
        torch.manual_seed(0)
        policy = make_policy("equidiff", get_preset("tiny"), WS)
        start = {k: v.clone() for k, v in policy.model.state_dict().items()}
        with previous_optimizer_step() if name == "loop" else contextlib.nullcontext():
            train(policy, ds, None, cfg, tmp_path / name)
        weights[name] = policy.model.state_dict()
        groups = load_training_checkpoint(tmp_path / name / "last.ckpt")["optimizer"]["param_groups"]
        assert all(bool(g["fused"]) == (name == "fused") for g in groups)
    moved = [k for k, v in weights["fused"].items() if v.is_floating_point() and not torch.equal(v, start[k])]
    assert len(moved) > 10  # the comparison covers weights that trained
    # within a tenth of one step's size (lr): where a gradient is near AdamW's eps, its division magnifies the
    # kernels' different rounding to a few % of a step; a wrong update (no bias correction, say) is off by half one
    for key in moved:
        torch.testing.assert_close(weights["fused"][key], weights["loop"][key], rtol=0, atol=1e-4)


def test_a_checkpoint_loads_with_the_ema_weights_that_training_exported(tmp_path):
    """A run with an EMA exports the averaged weights to policy.pt; ``load_policy_from_checkpoint``
    on its last.ckpt must give that same policy (it gave the raw training weights, so
    ``equidiff check-equivariance --checkpoint last.ckpt`` measured weights no robot runs)."""
    from equidiff_core.policy.file import read_policy_file

    ds = CubeDataset(3, seed=6)
    trained = make_policy("baseline", get_preset("tiny"), WS)
    train(trained, ds, None, _quick_cfg(steps=3, ema=True, eval_every=0), tmp_path)
    _, exported = read_policy_file(tmp_path / "policy.pt")  # the baseline exports its own layout

    averaged = load_policy_from_checkpoint(tmp_path / "last.ckpt").model.state_dict()
    raw = load_policy_from_checkpoint(tmp_path / "last.ckpt", ema=False).model.state_dict()
    assert averaged.keys() == exported.keys()
    for key, value in exported.items():
        torch.testing.assert_close(averaged[key], value)
    for key, value in trained.model.state_dict().items():
        torch.testing.assert_close(raw[key], value)
    assert any(not torch.equal(averaged[k], raw[k]) for k in raw)  # 3 steps: the average still lags


def test_checkpoints_hold_the_learned_state_whichever_mode_the_model_was_in(tmp_path):
    # escnn caches expanded filters as buffers in eval mode only. A save between validations (train
    # mode) and one right after validation (eval mode) must write the same keys, without the caches,
    # and both must resume into a freshly built model.
    ds = CubeDataset(3, seed=5)
    learned_keys = set(make_policy("equidiff", get_preset("tiny"), WS).train().model.state_dict())
    saved_keys = []
    for steps, eval_every in ((1, 0), (2, 2)):  # step 1 saved in train mode, step 2 after validation
        train(
            make_policy("equidiff", get_preset("tiny"), WS),
            ds,
            None,
            _quick_cfg(steps=steps, eval_every=eval_every, checkpoint_every=0),
            tmp_path,
        )
        saved_keys.append(set(load_training_checkpoint(tmp_path / "last.ckpt")["model"]))
    assert saved_keys[0] == saved_keys[1] == learned_keys
    assert not any(k.endswith((".filter", ".expanded_bias")) for k in learned_keys)

    # a checkpoint written before this fix carries the caches: it still loads, to the same weights
    path = tmp_path / "last.ckpt"
    restored = load_policy_from_checkpoint(path)
    state = load_training_checkpoint(path)
    state["model"] = restored.eval().model.state_dict()
    assert any(k.endswith(".filter") for k in state["model"])
    state.pop("weights_sha256")  # written before checkpoints carried a hash: unhashed, still loads
    torch.save(state, tmp_path / "old.ckpt")
    old = load_policy_from_checkpoint(tmp_path / "old.ckpt")
    for a, b in zip(old.model.parameters(), restored.model.parameters(), strict=True):
        torch.testing.assert_close(a, b)
    vox, ee = ds[0]["voxels"][None], ds[0]["ee"][None]
    g = lambda: torch.Generator().manual_seed(0)
    torch.testing.assert_close(
        old.predict_action({"voxels": vox, "ee": ee}, generator=g())["action"],
        restored.predict_action({"voxels": vox, "ee": ee}, generator=g())["action"],
    )

    # any other stray key is still refused
    state["model"]["encoder.0.weights_typo"] = torch.zeros(1)
    torch.save(state, tmp_path / "bad.ckpt")
    with pytest.raises(CheckpointError, match="weights_typo"):
        load_policy_from_checkpoint(tmp_path / "bad.ckpt")


def test_a_checkpoint_shared_without_the_optimiser_still_loads_and_resumes_on_schedule(tmp_path):
    import shutil

    ds = CubeDataset(2, seed=4)
    cfg = _quick_cfg(steps=4, warmup_steps=1, ema=True, eval_every=0, checkpoint_every=2)

    class KeepStep2:  # last.ckpt as written after step 2 of the 4, before the run goes on
        def on_step(self, step, metrics):
            if step == 3:
                shutil.copy(tmp_path / "full" / "last.ckpt", tmp_path / "step2.ckpt")

    full = Recorder()
    train(make_policy("baseline", get_preset("tiny"), WS), ds, None, cfg, tmp_path / "full", [full, KeepStep2()])
    (tmp_path / "cut").mkdir()
    without_optimizer_state(tmp_path / "step2.ckpt", tmp_path / "cut" / "last.ckpt")

    shared, original = (load_training_checkpoint(tmp_path / f) for f in ("cut/last.ckpt", "step2.ckpt"))
    assert shared["optimizer"] is None and original["optimizer"]["state"]
    assert (tmp_path / "cut" / "last.ckpt").stat().st_size < 0.8 * (tmp_path / "step2.ckpt").stat().st_size
    assert shared["step"] == 2 and shared["ema"] is not None
    for a, b in zip(
        load_policy_from_checkpoint(tmp_path / "cut/last.ckpt").model.parameters(),
        load_policy_from_checkpoint(tmp_path / "step2.ckpt").model.parameters(),
        strict=True,
    ):
        torch.testing.assert_close(a, b)

    # resumed: steps 3 and 4 on the same schedule as the uninterrupted run, with moments of its own
    resumed = Recorder()
    policy = make_policy("baseline", get_preset("tiny"), WS)
    name = "unet.final_conv.1.weight"
    after_step = {}

    class Weights:
        def on_step(self, step, metrics):
            after_step[step] = policy.model.state_dict()[name].clone()

    train(policy, ds, None, cfg, tmp_path / "cut", [resumed, Weights()])
    assert [s for s, _ in resumed.steps] == [3, 4]
    assert [m["lr"] for _, m in resumed.steps] == [m["lr"] for s, m in full.steps if s > 2]
    history = json.loads((tmp_path / "cut" / "history.json").read_text())
    assert {"step": 2, "resumed": "without optimiser state: fresh AdamW moments"} in history
    assert load_training_checkpoint(tmp_path / "cut" / "last.ckpt")["optimizer"]["state"]  # saved whole again
    # step 3 already moved the weights: its learning rate is the schedule's, not a fresh optimiser's 0
    assert not torch.equal(after_step[3], shared["model"][name])


def test_ema_weights_are_exported_and_training_weights_kept(tmp_path):
    ds = CubeDataset(2, seed=3)
    policy = make_policy("baseline", get_preset("tiny"), WS)
    train(policy, ds, None, _quick_cfg(steps=3, ema=True, lr=1e-2, eval_every=0), tmp_path)
    state = load_training_checkpoint(tmp_path / "last.ckpt")
    exported = torch.load(tmp_path / "policy.pt", weights_only=True)["state_dict"]
    name = "unet.final_conv.1.weight"
    torch.testing.assert_close(state["model"][name], policy.model.state_dict()[name])  # raw weights stay in the model
    assert not torch.allclose(exported[name], state["model"][name])  # the averaged ones are exported


def test_a_time_budget_stops_training_with_a_checkpoint_and_an_export(tmp_path):
    ds = CubeDataset(2, seed=4)
    policy = make_policy("baseline", get_preset("tiny"), WS)
    result = train(policy, ds, None, _quick_cfg(steps=50, eval_every=0, checkpoint_every=0, max_minutes=1e-4), tmp_path)
    assert result.steps == 1  # the budget (6 ms) runs out during the first step
    assert load_training_checkpoint(result.checkpoint)["step"] == 1
    assert "time budget" in result.history[-1]["stopped"]
    assert load_inference_policy(result.exported).preset.name == "tiny"
    with pytest.raises(ValueError, match="max_minutes"):
        TrainConfig(max_minutes=0)


def test_config_and_device_errors():
    with pytest.raises(ConfigError, match="unknown key"):
        from_dict(TrainConfig, {"stepz": 3})
    assert from_dict(TrainConfig, {"steps": 5, "ema": True}).steps == 5
    with pytest.raises(ValueError, match="noise_repeats"):
        TrainConfig(noise_repeats=0)
    for lr in (0.0, -1e-4, float("nan")):
        with pytest.raises(ValueError, match="lr must be positive"):
            TrainConfig(lr=lr)
    assert resolve_device("cpu").type == "cpu"
    if not torch.cuda.is_available():
        with pytest.raises(TrainingError, match="CUDA"):
            resolve_device("cuda")
        assert resolve_device("auto").type == "cpu"


@pytest.mark.slow
def test_overfits_tiny_dataset(tmp_path):
    """Two demonstrations (different cubes and start poses): the diffusion loss falls and DDIM-16
    samples land near each demonstration's own trajectory, clearly nearer than the other's, where
    the untrained policy's land as far from both.

    The short version of `equidiff bench overfit` (1200 steps: within 1.5 cm, 3x nearer its own
    demo, the width within 3 cm). 600 steps; measured on the 2-core Xeon
    (2026-11-27, before the fused optimiser): the loss 6.0x lower, samples 3.1 and 3.4 cm from their own trajectory and 11.2
    and 8.3 cm from the other's, the width 96 and 80 mm off; untrained 12.5 / 12.3 cm and 42 cm."""
    from equidiff_core.benches.overfit import OverfitGate, run_overfit

    result = run_overfit(tmp_path, steps=600)
    print(result.as_dict())
    short = OverfitGate(loss_fall=4.0, own_m=0.06, other_ratio=1.5, width_m=0.2)
    assert short.failures(result) == []
    untrained = dataclasses.replace(result, errors=result.untrained_errors)
    assert len(short.failures(untrained)) == 4  # each demo: as far from its own as from the other, the width


def test_a_slim_checkpoint_is_the_smallest_file_that_reproduces_the_exported_policy(tmp_path):
    """What gets committed of a finished run: the exported (EMA) escnn weights only, a third of the
    expanded policy.pt and of last.ckpt; exported again on load it predicts exactly as policy.pt."""
    from equidiff_core.benches.training_runs import run_policy
    from equidiff_core.training.loop import slim_checkpoint

    ds = CubeDataset(3, seed=6)
    torch.manual_seed(0)
    policy = make_policy("equidiff", get_preset("tiny"), WS)
    train(policy, ds, None, _quick_cfg(steps=3, ema=True, eval_every=0), tmp_path / "run")
    (tmp_path / "run" / "policy.pt").rename(tmp_path / "exported.pt")
    slim = slim_checkpoint(tmp_path / "run" / "last.ckpt", tmp_path / "run" / "weights.ckpt")
    assert slim.stat().st_size < 0.5 * (tmp_path / "run" / "last.ckpt").stat().st_size
    assert slim.stat().st_size < 0.7 * (tmp_path / "exported.pt").stat().st_size  # compact: 5 MB against 16
    state = load_training_checkpoint(slim)
    assert state["optimizer"] is None and state["ema"] is None and state["step"] == 3
    (tmp_path / "run" / "last.ckpt").unlink()
    exported_again = run_policy(tmp_path / "run", tmp_path / "cache")
    assert exported_again == tmp_path / "cache" / "policy.pt"
    sample = ds[0]
    a, b = (load_inference_policy(p) for p in (tmp_path / "exported.pt", exported_again))
    vox, ee = sample["voxels"][0].numpy(), sample["ee"][0].numpy()
    np.testing.assert_array_equal(a.predict(vox, ee, seed=1), b.predict(vox, ee, seed=1))
    with pytest.raises(FileNotFoundError, match="weights.ckpt"):
        run_policy(tmp_path / "nothing", tmp_path / "cache2")
