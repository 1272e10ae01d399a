"""Presets, networks, normaliser, augmentation and action codec."""

import math

import numpy as np
import pytest
import torch

from equidiff_core import geometry
from equidiff_core.config import ConfigError, Workspace
from equidiff_core.models import action_space
from equidiff_core.models.baseline import matched_channels
from equidiff_core.models.equivariance import random_observation
from equidiff_core.models.plain import build_plain_encoder
from equidiff_core.models.sampling import (
    ActionCodec,
    make_inference_scheduler,
    make_train_scheduler,
)
from equidiff_core.policy import augment
from equidiff_core.policy.diffusion import PolicyInputError, count_parameters, make_policy
from equidiff_core.policy.normalizer import Normalizer, NormalizerError
from equidiff_core.policy.presets import PRESETS, encoder_sizes, get_preset, preset_from_dict
from equidiff_core.twin.config import load_twin_config

WS = Workspace()


def test_presets_round_trip_and_validate():
    for preset in PRESETS.values():
        assert preset_from_dict(preset.to_dict()) == preset
        assert preset.horizon == 16 and preset.n_obs_steps == 1 and preset.n_action_steps == 8
    paper = get_preset("paper")
    assert paper.encoder_channels == (8, 16, 16, 32, 32, 64, 64, 128)
    assert paper.down_dims == (256, 512, 1024) and paper.crop == 58 and paper.group_order == 8
    with pytest.raises(ConfigError, match="unknown preset"):
        get_preset("huge")
    with pytest.raises(ConfigError, match="control"):
        get_preset("tiny", control="velocity")
    with pytest.raises(ConfigError, match="preset.horizon"):
        preset_from_dict({**paper.to_dict(), "horizon": "16"})


def test_encoder_layouts_follow_the_official_code_and_keep_the_legacy_one():
    assert all(p.encoder_layout == "official" for p in PRESETS.values())
    # EquivariantVoxelEncoder58Cyclic: conv (no padding), pool, 2 convs, pool, conv (no padding), conv, pool,
    # 2 convs, pool, a learned 3^3 conv (no padding) down to 1
    assert encoder_sizes(58, "official") == [56, 28, 28, 28, 14, 12, 12, 6, 6, 6, 3, 1]
    assert encoder_sizes(58, "legacy") == [58, 29, 29, 27, 9, 9, 9, 3, 3, 3, 1, 1]
    assert encoder_sizes(64, "official")[-1] == -1
    for preset in PRESETS.values():
        for layout in ("official", "legacy"):
            p = preset.replace(encoder_layout=layout)
            enc = build_plain_encoder(p, [4, *p.encoder_channels])
            assert enc(torch.zeros(1, 4, 58, 58, 58)).shape == (1, p.encoder_channels[-1], 1, 1, 1)
    # a preset saved before the field existed (the shipped checkpoint's) was trained with the legacy layout
    old = {k: v for k, v in get_preset("compact").to_dict().items() if k != "encoder_layout"}
    assert preset_from_dict(old).encoder_layout == "legacy"
    assert preset_from_dict(get_preset("compact").to_dict()).encoder_layout == "official"
    with pytest.raises(ConfigError, match="encoder_layout"):
        get_preset("tiny", encoder_layout="resnet")


def test_observation_embedding_ends_in_a_relu_only_in_the_legacy_layout():
    # the official enc_out is a bare equivariant Linear: the U-Net's condition can be negative
    for layout, relu in (("official", False), ("legacy", True)):
        torch.manual_seed(0)
        policy = make_policy("equidiff", get_preset("tiny", encoder_layout=layout), WS)
        policy.set_normalizer(Normalizer.from_workspace(WS))
        plain = policy.model.export_plain()
        vox, ee = random_observation(policy, batch=2, seed=0)
        v, e = policy.prepare_input(vox, ee, "center")
        for model in (policy.model, plain):
            cond = model.encode_obs(v, e)
            assert bool((cond >= 0).all()) == relu


def test_parameter_counts_and_matched_baseline():
    # paper size: the paper reports ~66M without the wrist camera; we build the same layout.
    policy = make_policy("equidiff", get_preset("paper"), WS)
    n_equi = count_parameters(policy.model)
    assert 60e6 < n_equi < 75e6
    equi_enc = count_parameters(policy.model.encoder)
    plain_enc = count_parameters(build_plain_encoder(policy.preset, [4, *matched_channels(policy.preset)]))
    assert abs(plain_enc - equi_enc) / equi_enc < 0.1
    base = make_policy("baseline", get_preset("paper"), WS)
    assert abs(count_parameters(base.model) - n_equi) / n_equi < 0.1


def test_schedulers_follow_the_paper():
    p = get_preset("compact")
    train = make_train_scheduler(p)
    assert train.config.num_train_timesteps == 100 and train.config.beta_schedule == "squaredcos_cap_v2"
    assert train.config.prediction_type == "epsilon" and train.config.clip_sample
    ddim = make_inference_scheduler(p)
    assert len(ddim.timesteps) == 16
    np.testing.assert_allclose(ddim.alphas_cumprod.numpy(), train.alphas_cumprod.numpy())


def _actions(n, rng):
    yaw = rng.uniform(-np.pi, np.pi, n)
    R = np.stack([geometry.rotz(y) @ np.diag([1.0, -1.0, -1.0]) for y in yaw])
    pos = np.asarray(WS.center) + rng.uniform(-0.1, 0.1, (n, 3))
    return geometry.pose_to_action(geometry.make_pose(R, pos), rng.uniform(0, 0.08, n))


def test_normalizer_scheme_and_rotation_closure():
    rng = np.random.default_rng(0)
    acts, ee = _actions(200, rng), _actions(50, rng)
    n = Normalizer.fit(acts, ee, WS)
    x = n.normalize(acts)
    assert np.abs(x[:, 2]).max() == pytest.approx(1.0)  # z min-max
    assert np.linalg.norm(x[:, :2], axis=1).max() == pytest.approx(1.0)  # one shared xy radius
    np.testing.assert_array_equal(x[:, 3:], acts[:, 3:])  # rot6d and width untouched
    np.testing.assert_allclose(n.unnormalize(x), acts, atol=1e-12)
    # rotating about the workspace centre = rotating normalised xy: the network's rho1
    rot = geometry.rotate_action(acts, 0.7, WS.center)
    np.testing.assert_allclose(n.normalize(rot), x @ geometry.action_rep(0.7).T, atol=1e-12)
    assert Normalizer.from_dict(n.to_dict()) == n
    with pytest.raises(NormalizerError):
        Normalizer.fit(acts * np.nan, ee, WS)


@pytest.mark.parametrize("control", ["absolute", "relative"])
def test_action_codec_round_trip_and_equivariance(control):
    rng = np.random.default_rng(1)
    acts, ee = _actions(32, rng), _actions(2, rng)
    codec = ActionCodec(control, Normalizer.fit(acts, ee, WS))
    acts, ee = torch.from_numpy(acts).reshape(2, 16, 10), torch.from_numpy(ee)
    x = codec.encode(acts, ee)
    assert x.shape == (2, 16, action_space.dim_of(action_space.freqs_for(control)))
    assert x.abs().max() <= 1.0 + 1e-9
    torch.testing.assert_close(codec.decode(x, ee), acts)
    theta = 1.1
    rep = torch.from_numpy(action_space.rep_matrix(codec.freqs, theta))
    xg = codec.encode(geometry.rotate_action(acts, theta, WS.center), geometry.rotate_action(ee, theta, WS.center))
    torch.testing.assert_close(xg, x @ rep.T)


def test_crops():
    vox = torch.arange(64**3, dtype=torch.int32).reshape(1, 1, 64, 64, 64)
    c = augment.center_crop(vox, 58)
    assert c.shape[-3:] == (58, 58, 58) and c[0, 0, 0, 0, 0] == vox[0, 0, 3, 3, 3]
    # centred crop commutes with rot90: C4 stays exact after cropping
    torch.testing.assert_close(augment.center_crop(torch.rot90(vox, 1, (-3, -2)), 58), torch.rot90(c, 1, (-3, -2)))
    r = augment.random_crop(vox.expand(4, 1, 64, 64, 64), 58, torch.Generator().manual_seed(0))
    assert r.shape == (4, 1, 58, 58, 58)
    with pytest.raises(ValueError):
        augment.center_crop(vox[..., :40, :40, :40], 58)
    # the one input builder of training (random) and evaluation/deployment (centre): crop, then [0, 1]
    grids = torch.randint(0, 256, (3, 1, 4, 64, 64, 64), dtype=torch.uint8)
    torch.testing.assert_close(augment.voxel_input(grids, 58, "center"), augment.center_crop(grids, 58).float() / 255)
    crops = augment.voxel_input(grids, 58, "random", torch.Generator().manual_seed(1))
    assert crops.shape == (3, 1, 4, 58, 58, 58) and crops.dtype == torch.float32
    assert not torch.equal(crops, augment.voxel_input(grids, 58, "random", torch.Generator().manual_seed(2)))
    assert augment.voxel_input(grids, 58, "center", dtype=torch.bfloat16).dtype == torch.bfloat16
    with pytest.raises(ValueError, match="crop mode"):
        augment.voxel_input(grids, 58, "centre")


def test_rotation_augmentation_moves_voxels_and_actions_together():
    vox = torch.zeros(1, 1, 4, 64, 64, 64, dtype=torch.uint8)
    i, j, k = 50, 32, 10  # a voxel +x of the centre
    vox[0, 0, :, i, j, k] = 255
    point = WS.lower + (np.array([i, j, k]) + 0.5) * WS.voxel_size
    act = torch.from_numpy(geometry.pose_to_action(geometry.make_pose(np.eye(3), point), np.array(0.05)))
    act = act.reshape(1, 1, 10).expand(1, 16, 10).clone()
    ee = act[:, :1].clone()
    out_v, out_e, out_a = augment.random_rotation(vox, ee, act, "c4", WS.center, torch.Generator().manual_seed(3))
    idx = torch.nonzero(out_v[0, 0, 0]).squeeze(0).numpy()
    moved = WS.lower + (idx + 0.5) * WS.voxel_size
    np.testing.assert_allclose(out_a[0, 0, :3].numpy(), moved, atol=1e-9)  # the action still points at the voxel
    np.testing.assert_allclose(out_e[0, 0].numpy(), out_a[0, 0].numpy())
    assert not np.allclose(idx, [i, j, k])  # seed 3 draws a non-identity rotation


def test_bad_batches_are_rejected_with_clear_errors():
    policy = make_policy("baseline", get_preset("tiny"), WS)
    policy.set_normalizer(Normalizer.from_workspace(WS))
    good = {
        "voxels": torch.zeros(2, 1, 4, 64, 64, 64, dtype=torch.uint8),
        "ee": torch.zeros(2, 1, 10),
        "action": torch.zeros(2, 16, 10),
    }
    with pytest.raises(PolicyInputError, match="uint8"):
        policy.compute_loss({**good, "voxels": good["voxels"].float()})
    with pytest.raises(PolicyInputError, match="NaN"):
        policy.compute_loss({**good, "ee": torch.full((2, 1, 10), math.nan)})
    with pytest.raises(PolicyInputError, match="action"):
        policy.compute_loss({**good, "action": torch.zeros(2, 8, 10)})
    with pytest.raises(RuntimeError, match="normaliser"):
        make_policy("baseline", get_preset("tiny"), WS).compute_loss(good)
    with pytest.raises(ValueError, match="unknown policy"):
        make_policy("transformer", get_preset("tiny"), WS)


def test_two_observation_steps_train_and_stay_equivariant():
    from equidiff_core.models import equivariance

    policy = make_policy("equidiff", get_preset("tiny", n_obs_steps=2), WS)
    policy.set_normalizer(Normalizer.from_workspace(WS))
    vox, ee = equivariance.random_observation(policy, batch=2, seed=0)
    assert vox.shape[1] == 2
    action = ee[:, -1:].expand(2, 16, 10).clone()
    loss = policy.train().compute_loss({"voxels": vox, "ee": ee, "action": action})
    loss.backward()
    assert torch.isfinite(loss)
    policy.eval()
    out = policy.predict_action({"voxels": vox, "ee": ee})
    assert out["action"].shape == (2, 8, 10) and out["action_pred"].shape == (2, 16, 10)
    assert equivariance.noise_predictor_error(policy, math.pi / 2, batch=1, scene=load_twin_config().scene) < 1e-4


def test_unet_film_split_equals_its_film_linear():
    """step_films(t) + global_films(cond) is each block's Linear(Mish(cat(step embedding, cond)))."""
    from equidiff_core.models.unet1d import ConditionalUnet1D

    torch.manual_seed(0)
    unet = ConditionalUnet1D(input_dim=6, global_cond_dim=10, diffusion_step_embed_dim=16, down_dims=(8, 16))
    t, cond = torch.tensor([3, 70]), torch.randn(2, 10)
    step_emb = unet.diffusion_step_encoder(t)
    full = torch.cat([b.cond_encoder(torch.cat([step_emb, cond], dim=-1)) for b in unet.res_blocks], dim=-1)
    torch.testing.assert_close(unet.step_films(t) + unet.global_films(cond), full, rtol=1e-5, atol=1e-6)
    assert full.shape[1] == sum(unet.film_sizes)
