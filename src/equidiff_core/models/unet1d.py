"""Diffusion Policy's 1D temporal U-Net with FiLM conditioning (Chi et al., 2023).

Hand-written because diffusers' UNet1DModel has no global-condition FiLM path; the layout
(residual blocks of Conv1d + GroupNorm + Mish, FiLM scale and bias from the diffusion-step
embedding concatenated with the observation embedding) follows real-stanford/diffusion_policy's
ConditionalUnet1D so its sizes and parameter counts compare one to one. Plain torch only: the
inference export uses this module unchanged.
"""

from __future__ import annotations

import math

import torch
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
        super().__init__(nn.Conv1d(inp, out, kernel_size, padding=kernel_size // 2),
                         nn.GroupNorm(n_groups, out), nn.Mish())


class ConditionalResidualBlock1D(nn.Module):
    def __init__(self, inp: int, out: int, cond_dim: int, kernel_size: int, n_groups: int):
        super().__init__()
        self.blocks = nn.ModuleList([Conv1dBlock(inp, out, kernel_size, n_groups),
                                     Conv1dBlock(out, out, kernel_size, n_groups)])
        self.out_channels = out
        # FiLM: per-channel scale and bias predicted from the condition.
        self.cond_encoder = nn.Sequential(nn.Mish(), nn.Linear(cond_dim, out * 2))
        self.residual_conv = nn.Conv1d(inp, out, 1) if inp != out else nn.Identity()

    def forward(self, x: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        out = self.blocks[0](x)
        film = self.cond_encoder(cond).unsqueeze(-1)
        scale, bias = film[:, : self.out_channels], film[:, self.out_channels:]
        out = self.blocks[1](scale * out + bias)
        return out + self.residual_conv(x)


class ConditionalUnet1D(nn.Module):
    """(B, input_dim, T) noisy sample, (B,) diffusion step, (B, global_cond_dim) -> (B, input_dim, T)."""

    def __init__(self, input_dim: int, global_cond_dim: int, diffusion_step_embed_dim: int = 256,
                 down_dims: tuple[int, ...] = (256, 512, 1024), kernel_size: int = 5, n_groups: int = 8):
        super().__init__()
        dsed = diffusion_step_embed_dim
        self.diffusion_step_encoder = nn.Sequential(
            SinusoidalPosEmb(dsed), nn.Linear(dsed, dsed * 4), nn.Mish(), nn.Linear(dsed * 4, dsed))
        cond_dim = dsed + global_cond_dim
        dims = [input_dim, *down_dims]
        in_out = list(zip(dims[:-1], dims[1:]))
        mid = down_dims[-1]
        block = lambda i, o: ConditionalResidualBlock1D(i, o, cond_dim, kernel_size, n_groups)  # noqa: E731
        self.mid_modules = nn.ModuleList([block(mid, mid), block(mid, mid)])
        self.down_modules = nn.ModuleList()
        for i, (d_in, d_out) in enumerate(in_out):
            last = i == len(in_out) - 1
            self.down_modules.append(nn.ModuleList([
                block(d_in, d_out), block(d_out, d_out),
                nn.Conv1d(d_out, d_out, 3, 2, 1) if not last else nn.Identity()]))
        self.up_modules = nn.ModuleList()
        for i, (d_in, d_out) in enumerate(reversed(in_out[1:])):
            last = i == len(in_out) - 1
            self.up_modules.append(nn.ModuleList([
                block(d_out * 2, d_in), block(d_in, d_in),
                nn.ConvTranspose1d(d_in, d_in, 4, 2, 1) if not last else nn.Identity()]))
        start = down_dims[0]
        self.final_conv = nn.Sequential(Conv1dBlock(start, start, kernel_size, n_groups), nn.Conv1d(start, input_dim, 1))

    def forward(self, sample: torch.Tensor, timestep: torch.Tensor, global_cond: torch.Tensor) -> torch.Tensor:
        step_emb = self.diffusion_step_encoder[0](timestep).to(global_cond.dtype)  # sinusoid in fp32, then model dtype
        cond = torch.cat([self.diffusion_step_encoder[1:](step_emb), global_cond], dim=-1)
        x = sample
        skips = []
        for res1, res2, down in self.down_modules:
            x = res2(res1(x, cond), cond)
            skips.append(x)
            x = down(x)
        for res in self.mid_modules:
            x = res(x, cond)
        for res1, res2, up in self.up_modules:
            x = torch.cat((x, skips.pop()), dim=1)
            x = up(res2(res1(x, cond), cond))
        return self.final_conv(x)
