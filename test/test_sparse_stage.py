"""The encoder's first stage from the occupied voxels only (models.sparse_stage): the dense layers' function."""

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from equidiff_core.config import Workspace
from equidiff_core.models import sparse_stage
from equidiff_core.models.equivariance import random_observation
from equidiff_core.models.sparse_stage import conv_pool_occupied, dense_first_stage, sparse_first_stage_enabled
from equidiff_core.policy.diffusion import make_policy
from equidiff_core.policy.normalizer import Normalizer
from equidiff_core.policy.presets import get_preset


def sparse_grid(shape, fill, seed):
    """Random values at a ``fill`` share of the voxels (every channel of an occupied voxel set), zeros elsewhere."""
    rng = np.random.default_rng(seed)
    B, _, *size = shape
    occupied = rng.random((B, 1, *size)) < fill
    occupied[:, :, 0, 0, 0] = True  # a corner voxel: only one output reaches it
    occupied[:, :, -1, -1, -1] = True  # and the far corner, which a floor-pooled odd grid drops
    return torch.from_numpy((rng.uniform(0.1, 1.0, shape) * occupied).astype(np.float32))


@pytest.mark.parametrize(
    "shape, fill, threshold, computed",
    [
        ((2, 4, 14, 14, 14), 0.1, 1.0, "sparse"),  # the sparse path on small grids, however many cells are reached
        ((1, 4, 13, 11, 12), 0.1, 1.0, "sparse"),  # odd sizes: the floor-pooled max-pool drops the last outputs
        ((3, 2, 8, 9, 10), 0.2, 1.0, "sparse"),
        ((2, 4, 30, 30, 30), 0.003, None, "sparse"),  # few voxels: sparse at the shipped threshold
        ((1, 4, 12, 12, 12), 0.6, None, "dense"),  # voxels everywhere: the dense layers
    ],
)
def test_matches_the_dense_convolution_and_max_pool_with_their_gradients(shape, fill, threshold, computed, monkeypatch):
    dense_calls, conv3d = [], F.conv3d
    monkeypatch.setattr(sparse_stage.F, "conv3d", lambda *a: dense_calls.append(1) or conv3d(*a))
    if threshold is not None:
        monkeypatch.setattr(sparse_stage, "DENSE_ABOVE_REACHED", threshold)
    x = sparse_grid(shape, fill, seed=sum(shape))
    gen = torch.Generator().manual_seed(0)
    weight = torch.randn((8, shape[1], 3, 3, 3), generator=gen, requires_grad=True)
    bias = torch.randn(8, generator=gen, requires_grad=True)
    upstream = torch.randn(F.max_pool3d(conv3d(x, weight, bias), 2).shape, generator=gen)

    dense = F.max_pool3d(conv3d(x, weight, bias), 2)
    dense_grads = torch.autograd.grad((dense * upstream).sum(), (weight, bias))
    out = conv_pool_occupied(x, weight, bias)
    grads = torch.autograd.grad((out * upstream).sum(), (weight, bias))

    assert ("dense" if dense_calls else "sparse") == computed
    assert out.shape == dense.shape
    assert computed == "dense" or out.is_contiguous(memory_format=torch.channels_last_3d)
    torch.testing.assert_close(out, dense, rtol=1e-5, atol=1e-5)
    for got, want in zip(grads, dense_grads):
        torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-4)


def test_an_empty_grid_gives_the_bias_and_only_the_bias_learns():
    x = torch.zeros(2, 4, 10, 10, 10)
    weight = torch.randn(8, 4, 3, 3, 3, requires_grad=True)
    bias = torch.randn(8, requires_grad=True)
    out = conv_pool_occupied(x, weight, bias)
    torch.testing.assert_close(out, bias.detach()[None, :, None, None, None].expand(2, 8, 4, 4, 4))
    grad_weight, grad_bias = torch.autograd.grad(out.sum(), (weight, bias))
    assert not grad_weight.any()
    torch.testing.assert_close(grad_bias, torch.full((8,), 2 * 4.0**3))


def test_refuses_what_it_cannot_compute():
    x = torch.zeros(1, 4, 8, 8, 8)
    with pytest.raises(ValueError, match="does not differentiate its input"):
        conv_pool_occupied(x.requires_grad_(), torch.zeros(8, 4, 3, 3, 3), torch.zeros(8))
    with pytest.raises(ValueError, match="filter"):
        conv_pool_occupied(torch.zeros(1, 4, 8, 8, 8), torch.zeros(8, 4, 5, 5, 5), torch.zeros(8))
    with pytest.raises(ValueError, match="on the CPU"):
        conv_pool_occupied(torch.zeros(1, 4, 8, 8, 8, device="meta"), torch.zeros(8, 4, 3, 3, 3), torch.zeros(8))
    with pytest.raises(ValueError, match="fp32 grids"):
        conv_pool_occupied(torch.zeros(1, 4, 8, 8, 8, dtype=torch.float64), torch.zeros(8, 4, 3, 3, 3), torch.zeros(8))


def test_a_voxel_is_occupied_when_any_channel_is_non_zero():
    x = torch.zeros(2, 4, 3, 3, 3)
    x[0, 3, 0, 0, 0] = 1e-30  # one channel, the smallest values included
    x[1, 0, 2, 1, 0] = -0.5
    x[1, 2, 1, 1, 1] = float("nan")  # not zero: the dense convolution would spread it
    x[0, 1, 2, 2, 2] = -0.0  # zero
    x = x.transpose(2, 4)  # any layout
    assert torch.equal(sparse_stage._occupied(x), x.ne(0).any(1))
    assert sparse_stage._occupied(x).sum() == 3


def test_the_dense_layers_stay_where_the_sparse_stage_was_not_measured():
    grid = torch.zeros(1, 4, 8, 8, 8)
    assert sparse_first_stage_enabled(grid)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        assert not sparse_first_stage_enabled(grid)
    with dense_first_stage():
        assert not sparse_first_stage_enabled(grid)
    assert not sparse_first_stage_enabled(grid.double())
    with torch.no_grad():  # inference, distillation's frozen encoder
        assert not sparse_first_stage_enabled(grid)
    while_traced = []  # deployment traces its network: the sparse stage's shapes would be frozen into it

    def network(g):
        while_traced.append(sparse_first_stage_enabled(g))
        return g * 2

    torch.jit.trace(network, grid)
    assert while_traced and not any(while_traced)


@pytest.fixture
def sparse_calls(monkeypatch):
    """How many times the sparse stage ran since the test began."""
    calls, apply = [], sparse_stage._ConvPoolOccupied.apply
    monkeypatch.setattr(sparse_stage._ConvPoolOccupied, "apply", lambda *a: calls.append(1) or apply(*a))
    return calls


def compact_policy(name="equidiff"):
    preset, ws = get_preset("compact"), Workspace()
    torch.manual_seed(0)
    policy = make_policy(name, preset, ws)
    policy.set_normalizer(Normalizer.from_workspace(ws))
    # observations of the training grids' sparsity, centre-cropped to 58³ (the first stage: 56³, pooled 28³)
    vox, ee = random_observation(policy, batch=2, seed=3, fill=0.03)
    return policy, *policy.prepare_input(vox, ee, "center")


@pytest.mark.parametrize("name", ["equidiff", "baseline"])  # escnn's expanded filter; plain Conv3d weights
def test_each_encoder_is_the_same_function_and_learns_the_same(name, sparse_calls):
    policy, x, ee = compact_policy(name)
    policy.train()  # escnn expands the filter from the weights at every call
    model = policy.model

    def encode_and_grads():
        model.zero_grad()
        cond = model.encode_obs(x, ee)
        cond.square().sum().backward()
        return cond.detach(), {n: p.grad.clone() for n, p in model.named_parameters() if p.grad is not None}

    sparse, sparse_grads = encode_and_grads()
    assert len(sparse_calls) == 1
    with dense_first_stage():
        dense, dense_grads = encode_and_grads()
    assert len(sparse_calls) == 1
    with torch.no_grad():
        assert not torch.equal(sparse, model.encode_obs(torch.zeros_like(x), ee))  # the voxels matter
    torch.testing.assert_close(sparse, dense, rtol=1e-4, atol=1e-5)
    assert sparse_grads.keys() == dense_grads.keys() and any("encoder" in n for n in sparse_grads)
    for param, want in dense_grads.items():  # fp32 sums of thousands of terms: the error scales with the largest
        scale = float(want.abs().max())
        torch.testing.assert_close(sparse_grads[param], want, rtol=1e-3, atol=max(1e-5, 2e-6 * scale), msg=param)


def test_the_escnn_encoder_in_eval_mode_uses_its_cached_filter(sparse_calls):
    policy, x, ee = compact_policy()
    policy.eval()
    sparse = policy.model.encode_obs(x, ee).detach()  # gradients on: the sparse stage, through the cached filter
    assert len(sparse_calls) == 1
    with torch.no_grad():
        dense = policy.model.encode_obs(x, ee)
    assert len(sparse_calls) == 1
    torch.testing.assert_close(sparse, dense, rtol=1e-4, atol=1e-5)
