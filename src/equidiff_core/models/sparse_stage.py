"""The voxel encoder's first stage (a 3³ convolution without padding, then a 2³ max-pool) computed from the
occupied voxels only, on the CPU while training (EquiDiff's escnn encoder and the baseline's plain one): the same
function as the dense layers, in a fraction of the work.

Why it is exact: an empty voxel (all channels 0) adds nothing to a convolution, so each output is the bias plus
the sum, over the occupied voxels within its 3³ window, of the filter's tap times that voxel. Each occupied voxel
therefore adds its 27 taps into the outputs it reaches (``index_add_``); every output no voxel reaches is the bias
alone. The pooled value is the largest of a cell's 8 outputs; adding the bias after the maximum is the same,
since rounding is monotone. The sums run in another order than oneDNN's, so results agree to fp32 rounding.

Why it pays: about 2 % of the grid is occupied in the twin's frames, while the dense first convolution, its
backward, the 56³ max-pool and its gradient were the largest items of a CPU training step (docs/results/model.md,
"What a CPU training step costs"). Written here rather than taken from a sparse-convolution library: spconv and
MinkowskiEngine are compiled dependencies built around CUDA, with sparse outputs the dense max-pool and escnn's
expanded filter would still have to be fitted around; this is torch's ``index_add_`` and a matrix product.

``dense_first_stage()`` switches it off (the dense layers, as before), for the benches' comparison.
"""

from __future__ import annotations

import contextlib
from contextvars import ContextVar

import torch
import torch.nn.functional as F

_DENSE_FIRST_STAGE: ContextVar[bool] = ContextVar("dense_first_stage", default=False)


@contextlib.contextmanager
def dense_first_stage():
    """Encoders run inside compute their first stage densely, as before this module (``equidiff bench train
    --variants dense_first_stage``)."""
    token = _DENSE_FIRST_STAGE.set(True)
    try:
        yield
    finally:
        _DENSE_FIRST_STAGE.reset(token)


def sparse_first_stage_enabled(x: torch.Tensor) -> bool:
    """Whether ``conv_pool_occupied`` should compute the first stage for input ``x``: while training (gradients
    on, not traced: deployment's exported, traced network and every no-grad pass keep oneDNN's dense layers), an
    fp32 grid on the CPU (never a gradient for it; bf16 autocast keeps the dense layers it was measured with),
    unless ``dense_first_stage()`` is in force."""
    return (
        torch.is_grad_enabled()
        and not torch.jit.is_tracing()
        and x.device.type == "cpu"
        and x.dtype == torch.float32
        and not x.requires_grad
        and not torch.is_autocast_enabled("cpu")
        and not _DENSE_FIRST_STAGE.get()
    )


def is_conv_pool_stage(conv, pool) -> bool:
    """Whether ``conv`` then ``pool`` is the stage ``conv_pool_occupied`` computes: a biased 3³ convolution
    without padding, then a 2³ max-pool (torch's Conv3d / MaxPool3d or escnn's R3Conv / PointwiseMaxPool3D,
    whose sizes are ints or triples)."""
    triple = torch.nn.modules.utils._triple
    return (
        triple(conv.kernel_size) == (3, 3, 3)
        and triple(conv.padding) == (0, 0, 0)
        and triple(conv.stride) == triple(conv.dilation) == (1, 1, 1)
        and conv.groups == 1
        and conv.bias is not None
        and triple(pool.kernel_size) == triple(pool.stride) == (2, 2, 2)
        and triple(pool.padding) == (0, 0, 0)
        and triple(pool.dilation) == (1, 1, 1)
        and not pool.ceil_mode
    )


# The 3³ window's taps (a, b, c) in the filter's order (a slowest): output o sees input o + (a, b, c).
_TAPS = torch.stack(torch.meshgrid(*[torch.arange(3)] * 3, indexing="ij"), -1).reshape(27, 3)
_PARITIES = _TAPS[[0, 1, 3, 4, 9, 10, 12, 13]]  # (q0, q1, q2) in {0, 1}³, numbered 4 q0 + 2 q1 + q2


def _tap_rows(pooled: tuple[int, int, int]) -> torch.Tensor:
    """(8, 27): the row of tap t of a voxel of parity q, relative to 8 x the cell of (voxel // 2).

    A voxel p = 2 h + q reaches output o = p - a, whose cell is h + (q - a) // 2 along each axis and whose
    place in the cell is (q - a) % 2: both depend on q and a only, so one table serves every voxel."""
    d = (_PARITIES[:, None, :] - _TAPS[None]).div(2, rounding_mode="floor")  # (8, 27, 3) cell steps
    child = (_PARITIES[:, None, :] - _TAPS[None]) % 2
    _, P1, P2 = pooled
    return ((d[..., 0] * P1 + d[..., 1]) * P2 + d[..., 2]) * 8 + child[..., 0] * 4 + child[..., 1] * 2 + child[..., 2]


# Above this share of pooled cells reached (voxels scattered all over the grid, as random noise is) the dense
# layers are the cheaper way to the same function (the break-even swept in docs/results/model.md, "What a CPU
# training step costs").
DENSE_ABOVE_REACHED = 0.85


def _occupied(x: torch.Tensor) -> torch.Tensor:
    """(B, D, H, W): whether any channel of the fp32 grid ``x`` is non-zero (NaN counts, -0.0 does not), as
    ``x.ne(0).any(1)``. Its channels' bit patterns OR-ed, the sign bit masked: one pass over the grid, where
    ``ne(0).any(1)`` writes a boolean grid and reduces it across the channels in a second."""
    bits = x.view(torch.int32)
    merged = bits[:, 0].clone()
    for channel in range(1, x.shape[1]):
        merged |= bits[:, channel]
    return (merged & 0x7FFFFFFF) != 0


def _plan(x: torch.Tensor):
    """(feats (M, C) of the M occupied voxels, rows (27, M): the output row each tap adds to, numbered by
    reached cell, 8 rows a cell, a spare last row for taps outside; reached (R,): those cells' flat indices,
    pooled size, cells) for a grid (B, C, D, H, W)."""
    B, _, *size = x.shape
    pooled = tuple((n - 2) // 2 for n in size)  # a 3³ convolution without padding, then floor pooling
    cells = B * pooled[0] * pooled[1] * pooled[2]
    where = _occupied(x).nonzero()  # (M, 4): sample, then the voxel's three indices
    sample, voxel = where[:, 0], where[:, 1:]
    feats = x.permute(0, 2, 3, 4, 1)[sample, voxel[:, 0], voxel[:, 1], voxel[:, 2]]
    half, parity = voxel.div(2, rounding_mode="floor"), voxel % 2
    cell = ((sample * pooled[0] + half[:, 0]) * pooled[1] + half[:, 1]) * pooled[2] + half[:, 2]
    # each output's row, grouped by pooled cell so that the max-pool reduces contiguous rows; a tap whose
    # output lies outside the pooled outputs goes to the spare row
    rows = 8 * cell[:, None] + _tap_rows(pooled)[parity @ torch.tensor([4, 2, 1])]  # (M, 27)
    reach = voxel[:, :, None] - torch.arange(3)  # (M, 3 axes, 3 taps): the output index along each axis
    inside = [(reach[:, i] >= 0) & (reach[:, i] < 2 * n) for i, n in enumerate(pooled)]
    inside = (inside[0][:, :, None, None] & inside[1][:, None, :, None] & inside[2][:, None, None, :]).view(-1, 27)
    rows = torch.where(inside, rows, cells * 8).t().contiguous()  # (27, M)
    # Only the cells some tap reaches get rows (numbered in order); every other cell's outputs are 0 before
    # the bias, so it pools to the bias alone.
    reached = torch.zeros(cells + 1, dtype=torch.bool)
    reached[rows.view(-1) >> 3] = True
    reached = reached[:-1].nonzero().squeeze(1)
    numbered = torch.full((cells + 1,), len(reached), dtype=torch.long)
    numbered[reached] = torch.arange(len(reached))
    rows = numbered[rows >> 3] * 8 + (rows & 7)  # the spare row is now len(reached) * 8
    return feats, rows, reached, (B, *pooled), cells


class _ConvPoolOccupied(torch.autograd.Function):
    @staticmethod
    def forward(ctx, feats, rows, reached, shape, cells, weight: torch.Tensor, bias: torch.Tensor):
        C, Co = feats.shape[1], weight.shape[0]
        outputs = feats.new_zeros(len(reached) * 8 + 1, Co)
        taps = weight.permute(2, 3, 4, 1, 0).reshape(27, C, Co)
        for tap in range(27):  # one tap at a time: its (M, Co) products stay in cache for the scatter
            outputs.index_add_(0, rows[tap], feats @ taps[tap])
        reached_max, child_max = outputs[:-1].view(len(reached), 8, Co).max(1)
        # channels-last, as oneDNN's first convolution leaves it: the later convolutions and their backward
        # run several times faster on it than on the contiguous layout (docs/results/model.md)
        out = torch.empty((shape[0], Co, *shape[1:]), dtype=feats.dtype, memory_format=torch.channels_last_3d)
        per_cell = out.permute(0, 2, 3, 4, 1).view(cells, Co)  # the same memory, a row per cell
        per_cell.copy_(bias.expand(cells, Co))
        per_cell[reached] = reached_max + bias
        ctx.save_for_backward(feats, rows, reached, child_max)
        return out

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        feats, rows, reached, child_max = ctx.saved_tensors
        Co = child_max.shape[1]
        per_cell = grad.permute(0, 2, 3, 4, 1).reshape(-1, Co)
        # the max-pool's gradient: each reached cell's to its largest output (the spare row stays 0)
        per_output = per_cell.new_zeros(len(reached) * 8 + 1, Co)
        per_output[:-1].view(-1, 8, Co).scatter_(1, child_max[:, None], per_cell[reached][:, None])
        grad_taps = torch.stack([feats.t() @ per_output[rows[tap]] for tap in range(27)])  # (27, C, Co)
        grad_weight = grad_taps.view(3, 3, 3, -1, Co).permute(4, 3, 0, 1, 2)
        return None, None, None, None, None, grad_weight, per_cell.sum(0)


def conv_pool_occupied(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    """``max_pool3d(conv3d(x, weight, bias), 2)`` for a 3³ ``weight`` (stride 1, no padding), from the voxels of
    ``x`` (B, C, D, H, W) with any channel non-zero; differentiable in ``weight`` and ``bias``, not in ``x``."""
    if x.requires_grad:
        raise ValueError("conv_pool_occupied does not differentiate its input")
    if x.device.type != "cpu" or x.dtype != torch.float32:
        raise ValueError(f"conv_pool_occupied runs on fp32 grids on the CPU, got {x.dtype} on {x.device}")
    if weight.shape[2:] != (3, 3, 3) or weight.shape[1] != x.shape[1] or bias.shape != weight.shape[:1]:
        raise ValueError(
            f"expected a (Co, {x.shape[1]}, 3, 3, 3) filter and a (Co,) bias, got "
            f"{tuple(weight.shape)} and {tuple(bias.shape)}"
        )
    feats, rows, reached, shape, cells = _plan(x)
    if len(reached) > DENSE_ABOVE_REACHED * cells:
        return F.max_pool3d(F.conv3d(x, weight, bias), 2)
    return _ConvPoolOccupied.apply(feats, rows, reached, shape, cells, weight, bias)
