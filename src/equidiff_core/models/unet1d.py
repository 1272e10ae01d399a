"""Diffusion Policy's 1D temporal U-Net with FiLM conditioning (Chi et al., 2023).

Hand-written because diffusers' UNet1DModel has no global-condition FiLM path; the layout
(residual blocks of Conv1d + GroupNorm + Mish, FiLM scale and bias from the diffusion-step
embedding concatenated with the observation embedding) follows real-stanford/diffusion_policy's
ConditionalUnet1D so its sizes and parameter counts compare one to one. Plain torch only: the
inference export uses this module unchanged.
"""

from __future__ import annotations

import itertools
import math

import torch
import torch.nn.functional as F
from torch import nn


class SinusoidalPosEmb(nn.Module):
    def __init__(self, dim: int):
        super().__init__()
        self.dim = dim

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        half = self.dim // 2
        scale = math.log(10000) / (half - 1)
        freqs = torch.exp(torch.arange(half, device=x.device, dtype=torch.float32) * -scale)
        emb = x.float()[:, None] * freqs[None, :]
        return torch.cat((emb.sin(), emb.cos()), dim=-1)


class Conv1dBlock(nn.Sequential):
    def __init__(self, inp: int, out: int, kernel_size: int, n_groups: int):
        super().__init__(
            nn.Conv1d(inp, out, kernel_size, padding=kernel_size // 2), nn.GroupNorm(n_groups, out), nn.Mish()
        )


class ConditionalResidualBlock1D(nn.Module):
    def __init__(self, inp: int, out: int, cond_dim: int, kernel_size: int, n_groups: int):
        super().__init__()
        self.blocks = nn.ModuleList(
            [Conv1dBlock(inp, out, kernel_size, n_groups), Conv1dBlock(out, out, kernel_size, n_groups)]
        )
        self.out_channels = out
        # FiLM: per-channel scale and bias predicted from the condition (Mish, then Linear; the
        # U-Net evaluates this Linear in two parts: ConditionalUnet1D.step_films and global_films).
        self.cond_encoder = nn.Sequential(nn.Mish(), nn.Linear(cond_dim, out * 2))
        self.residual_conv = nn.Conv1d(inp, out, 1) if inp != out else nn.Identity()

    def forward(self, x: torch.Tensor, film: torch.Tensor) -> torch.Tensor:
        """x (B, inp, T), film (B, 2 * out): this block's FiLM scale and bias."""
        out = self.blocks[0](x)
        film = film.unsqueeze(-1)
        scale, bias = film[:, : self.out_channels], film[:, self.out_channels :]
        # one fused op: bf16 `scale * out + bias` broadcast over time ran slower on CPU (measured)
        out = self.blocks[1](torch.addcmul(bias, scale, out))
        return out + self.residual_conv(x)


class ConditionalUnet1D(nn.Module):
    """(B, input_dim, T) noisy sample, (B,) diffusion step, (B, global_cond_dim) -> (B, input_dim, T)."""

    def __init__(
        self,
        input_dim: int,
        global_cond_dim: int,
        diffusion_step_embed_dim: int = 256,
        down_dims: tuple[int, ...] = (256, 512, 1024),
        kernel_size: int = 5,
        n_groups: int = 8,
    ):
        super().__init__()
        dsed = diffusion_step_embed_dim
        self.diffusion_step_encoder = nn.Sequential(
            SinusoidalPosEmb(dsed), nn.Linear(dsed, dsed * 4), nn.Mish(), nn.Linear(dsed * 4, dsed)
        )
        cond_dim = dsed + global_cond_dim
        dims = [input_dim, *down_dims]
        in_out = list(itertools.pairwise(dims))
        mid = down_dims[-1]
        block = lambda i, o: ConditionalResidualBlock1D(i, o, cond_dim, kernel_size, n_groups)
        self.mid_modules = nn.ModuleList([block(mid, mid), block(mid, mid)])
        self.down_modules = nn.ModuleList()
        for i, (d_in, d_out) in enumerate(in_out):
            last = i == len(in_out) - 1
            self.down_modules.append(
                nn.ModuleList(
                    [
                        block(d_in, d_out),
                        block(d_out, d_out),
                        nn.Conv1d(d_out, d_out, 3, 2, 1) if not last else nn.Identity(),
                    ]
                )
            )
        self.up_modules = nn.ModuleList()
        for i, (d_in, d_out) in enumerate(reversed(in_out[1:])):
            last = i == len(in_out) - 1
            self.up_modules.append(
                nn.ModuleList(
                    [
                        block(d_out * 2, d_in),
                        block(d_in, d_in),
                        nn.ConvTranspose1d(d_in, d_in, 4, 2, 1) if not last else nn.Identity(),
                    ]
                )
            )
        start = down_dims[0]
        self.final_conv = nn.Sequential(
            Conv1dBlock(start, start, kernel_size, n_groups), nn.Conv1d(start, input_dim, 1)
        )
        self.res_blocks = [
            m
            for level in (*self.down_modules, self.mid_modules, *self.up_modules)
            for m in level
            if isinstance(m, ConditionalResidualBlock1D)
        ]
        self.film_sizes = [2 * b.out_channels for b in self.res_blocks]

    # FiLM of all residual blocks, concatenated: films = step_films(t) + global_films(cond). Each
    # block's Linear(Mish(cat(step_emb, cond))) splits exactly into a step part and a condition
    # part (Mish is elementwise), so a sampler computes the condition part once per observation
    # and the step part once per timestep instead of both at every denoising step.
    def step_films(self, timestep: torch.Tensor) -> torch.Tensor:
        """(B,) diffusion steps -> (B, sum(film_sizes)), including the Linear biases."""
        enc = self.diffusion_step_encoder
        step_emb = enc[0](timestep).to(enc[1].weight.dtype)  # sinusoid in fp32, then model dtype
        h = F.mish(enc[1:](step_emb))
        dsed = h.shape[-1]
        return torch.cat(
            [F.linear(h, b.cond_encoder[1].weight[:, :dsed], b.cond_encoder[1].bias) for b in self.res_blocks], dim=-1
        )

    def global_films(self, global_cond: torch.Tensor) -> torch.Tensor:
        """(B, global_cond_dim) -> (B, sum(film_sizes)), without biases (step_films has them)."""
        h = F.mish(global_cond)
        dsed = self.diffusion_step_encoder[-1].out_features
        return torch.cat([F.linear(h, b.cond_encoder[1].weight[:, dsed:]) for b in self.res_blocks], dim=-1)

    def films(self, timestep: torch.Tensor, global_cond: torch.Tensor) -> torch.Tensor:
        """All FiLM terms for (B,) or scalar diffusion steps and (B*k, global_cond_dim) conditions:
        each step's row is repeated for the k consecutive condition rows it belongs to (EquiDiff's
        group elements)."""
        steps = self.step_films(timestep.reshape(-1))
        rows = global_cond.shape[0]
        if steps.shape[0] != rows:
            steps = steps.repeat_interleave(rows // steps.shape[0], dim=0)
        return steps + self.global_films(global_cond)

    def forward(self, sample: torch.Tensor, timestep: torch.Tensor, global_cond: torch.Tensor) -> torch.Tensor:
        return self.forward_films(sample, self.films(timestep, global_cond))

    def forward_films(self, sample: torch.Tensor, films: torch.Tensor) -> torch.Tensor:
        """(B, input_dim, T) noisy sample, (B, sum(film_sizes)) from step_films + global_films."""
        film = iter(films.split(self.film_sizes, dim=-1))
        x = sample
        skips = []
        for res1, res2, down in self.down_modules:
            x = res2(res1(x, next(film)), next(film))
            skips.append(x)
            x = down(x)
        for res in self.mid_modules:
            x = res(x, next(film))
        for res1, res2, up in self.up_modules:
            x = torch.cat((x, skips.pop()), dim=1)
            x = up(res2(res1(x, next(film)), next(film)))
        return self.final_conv(x)
