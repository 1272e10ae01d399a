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


_TAP = torch.arange(3)[:, None]  # a tap's offset along one axis: output o sees input o + a
# Steps back from a voxel's cell h to the 8 cells whose 4³ input window holds the voxel: h or h - 1 along each axis.
_CELLS_BACK = torch.tensor([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)])


# Above this share of pooled cells reached (voxels scattered all over the grid, as random noise is) the dense
# layers are the cheaper way to the same function (the break-even swept in docs/results/model.md, "What a CPU
# training step costs").
DENSE_ABOVE_REACHED = 0.95


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
    reached cell, 8 rows a cell, and 8 spare rows last for taps whose output the max-pool drops; reached (R,):
    those cells' flat indices, pooled size, cells) for a grid (B, C, D, H, W).

    Along each axis a voxel p = 2 h + q (q its parity) reaches, through tap a, output o = p - a, in cell
    h + (q - a) // 2 (h - 1 when a > q, else h) at place (q - a) % 2 = (q + a) % 2 of that cell's two. Cells are
    numbered in a grid padded by a ring of spare cells, where the outputs outside the pooled ones fall: no tap
    needs a bounds check. The (27, M) tensors are the plan's largest, so each is built by one broadcast sum of
    per-axis (3, M) terms and one gather."""
    B, _, *size = x.shape
    pooled = tuple((n - 2) // 2 for n in size)  # a 3³ convolution without padding, then floor pooling
    cells = B * pooled[0] * pooled[1] * pooled[2]
    where = _occupied(x).nonzero()  # (M, 4): sample, then the voxel's three indices
    feats = x.permute(0, 2, 3, 4, 1)[where.unbind(1)]
    sample, voxel = where[:, 0], where[:, 1:]
    padded = tuple((n - 1) // 2 + 2 for n in size)  # cells -1 .. (n - 1) // 2 along each axis, shifted by one
    strides = (padded[1] * padded[2], padded[2], 1)
    start = sample * (padded[0] * strides[0])  # each sample's first padded cell
    own_cell = start.clone()
    tap_cells, tap_places = [], []
    for axis in range(3):
        p = voxel[:, axis]
        half, parity = (p >> 1) + 1, p & 1  # the voxel's padded cell along the axis, and its place in it
        own_cell += half * strides[axis]
        tap_cells.append((half - (_TAP > parity).long()) * strides[axis])  # (3, M): each tap's output cell
        tap_places.append(((parity + _TAP) & 1) << (2 - axis))
    # A cell is reached when an occupied voxel lies in its 4³ input window (its 2³ outputs' 3³ windows): the
    # voxel's own cell and the 7 before it. Only reached cells get rows, numbered in order; every other cell's
    # outputs are 0 before the bias, so it pools to the bias alone.
    hit = torch.zeros(B * padded[0] * strides[0], dtype=torch.bool)
    hit[own_cell[:, None] - _CELLS_BACK @ torch.tensor(strides)] = True
    interior = (slice(None), *(slice(1, n + 1) for n in pooled))
    reached_map = hit.view(B, *padded)[interior]
    reached = reached_map.reshape(-1).nonzero().squeeze(1)
    numbered = torch.full((B, *padded), len(reached), dtype=torch.long)
    order = reached_map.reshape(-1).cumsum(0).sub_(1).view(B, *pooled)
    numbered[interior] = torch.where(reached_map, order, len(reached))
    c0, c1, c2 = tap_cells
    rows = numbered.view(-1)[(c0 + start)[:, None, None] + c1[None, :, None] + c2[None, None, :]]  # (3, 3, 3, M)
    p0, p1, p2 = tap_places
    rows.mul_(8).add_(p0[:, None, None]).add_(p1[None, :, None]).add_(p2[None, None, :])
    return feats, rows.view(27, -1), reached, (B, *pooled), cells


class _ConvPoolOccupied(torch.autograd.Function):
    @staticmethod
    def forward(ctx, feats, rows, reached, shape, cells, weight: torch.Tensor, bias: torch.Tensor):
        C, Co = feats.shape[1], weight.shape[0]
        outputs = feats.new_zeros(len(reached) * 8 + 8, Co)  # the last 8: the spare rows
        taps = weight.permute(2, 3, 4, 1, 0).reshape(27, C, Co)
        for tap in range(27):  # one tap at a time: its (M, Co) products stay in cache for the scatter
            outputs.index_add_(0, rows[tap], feats @ taps[tap])
        reached_max, child_max = outputs[:-8].view(len(reached), 8, Co).max(1)
        # channels-last, as oneDNN's first convolution leaves it: the later convolutions and their backward
        # run several times faster on it than on the contiguous layout (docs/results/model.md)
        out = torch.empty((shape[0], Co, *shape[1:]), dtype=feats.dtype, memory_format=torch.channels_last_3d)
        per_cell = out.permute(0, 2, 3, 4, 1).view(cells, Co)  # the same memory, a row per cell
        per_cell.copy_(bias.expand(cells, Co))
        per_cell.index_copy_(0, reached, reached_max + bias)
        ctx.save_for_backward(feats, rows, reached, child_max)
        return out

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        feats, rows, reached, child_max = ctx.saved_tensors
        Co = child_max.shape[1]
        per_cell = grad.permute(0, 2, 3, 4, 1).reshape(-1, Co)
        # the max-pool's gradient: each reached cell's to its largest output (the spare rows stay 0)
        per_output = per_cell.new_zeros(len(reached) * 8 + 8, Co)
        per_output[:-8].view(-1, 8, Co).scatter_(1, child_max[:, None], per_cell.index_select(0, reached)[:, None])
        # index_select: torch's row copy, faster here than indexing with a tensor
        grad_taps = torch.stack([feats.t() @ per_output.index_select(0, rows[tap]) for tap in range(27)])  # (27, C, Co)
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
