"""CPU speed-ups for the plain-torch networks at inference: same weights, same outputs, faster kernels.

``policy.inference.InferencePolicy`` applies them on CPU: the encoder's Conv3d run by oneDNN in
channels_last_3d (fp32; the old path pads the first Conv3d to 8 input channels instead), the U-Net's Conv1d and ConvTranspose1d as GEMMs (bf16) and a faster Mish; ``Method``
lets ``torch.jit.trace`` trace one method of a module.
"""

from __future__ import annotations

import torch


def pad_first_conv(encoder: torch.nn.Sequential, multiple: int) -> int:
    """Give the first Conv3d zero weights for extra input channels up to ``multiple``; returns how many.

    oneDNN's fp32 3D convolution on CPU takes a slow path for 4 input channels, several times slower
    than for 8 (docs/results/model.md, "What the denoising step does"); the padded channels are zeros, so the output is unchanged."""
    conv = encoder[0]
    extra = -conv.in_channels % multiple
    if not isinstance(conv, torch.nn.Conv3d) or extra == 0:
        return 0
    padded = torch.nn.Conv3d(
        conv.in_channels + extra,
        conv.out_channels,
        conv.kernel_size,
        conv.stride,
        conv.padding,
        bias=conv.bias is not None,
    ).to(conv.weight.device, conv.weight.dtype)
    with torch.no_grad():
        padded.weight.zero_()
        padded.weight[:, : conv.in_channels] = conv.weight
        if conv.bias is not None:
            padded.bias.copy_(conv.bias)
    encoder[0] = padded.eval()
    return extra


class OneDnnConv3d(torch.nn.Module):
    """A Conv3d always computed by oneDNN (``torch.mkldnn_convolution``): same weights, same output.

    For a batch of one, torch's dispatcher sends a 3D convolution with few channels on a small map
    (batch * channels * depth * height <= 20480, aten's ``use_mkldnn``) to its own vol2col + GEMM
    kernel, several times slower there than oneDNN on AVX2 and AVX-512 alike: most of the encoder's
    layers at 28³ and below (docs/results/model.md, "The encoder near the core's limit")."""

    def __init__(self, conv: torch.nn.Conv3d):
        super().__init__()
        if conv.padding_mode != "zeros" or isinstance(conv.padding, str):
            raise ValueError("OneDnnConv3d handles zero-padded convolutions with numeric padding only")
        self.weight, self.bias = conv.weight, conv.bias
        self.padding, self.stride, self.dilation, self.groups = conv.padding, conv.stride, conv.dilation, conv.groups

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.mkldnn_convolution(
            x, self.weight, self.bias, self.padding, self.stride, self.dilation, self.groups
        )


class MatmulConv1d(torch.nn.Module):
    """A Conv1d computed as one matrix product over unfolded windows (same weights, same output).

    The U-Net's convolutions see 4-16 time steps and 8 group elements per call, where oneDNN's
    bf16 Conv1d is slower than the equivalent GEMM (docs/results/model.md, "What the denoising step does");
    in fp32 the GEMM is not faster, so only bf16 uses this."""

    def __init__(self, conv: torch.nn.Conv1d):
        super().__init__()
        if conv.groups != 1 or conv.dilation[0] != 1 or conv.padding_mode != "zeros":
            raise ValueError("MatmulConv1d handles plain convolutions only")
        self.kernel, self.stride, self.padding = conv.kernel_size[0], conv.stride[0], conv.padding[0]
        out_ch, in_ch, k = conv.weight.shape
        # (out, in, k) -> (out, k*in), matching windows flattened as (k, in)
        self.weight = torch.nn.Parameter(
            conv.weight.detach().permute(0, 2, 1).reshape(out_ch, k * in_ch).contiguous(), requires_grad=False
        )
        self.bias = None if conv.bias is None else torch.nn.Parameter(conv.bias.detach().clone(), requires_grad=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.padding:
            x = torch.nn.functional.pad(x, (self.padding, self.padding))
        windows = x.unfold(2, self.kernel, self.stride)  # (B, C, T', k)
        B, C, T, k = windows.shape
        y = torch.nn.functional.linear(windows.permute(0, 2, 3, 1).reshape(B * T, k * C), self.weight, self.bias)
        return y.reshape(B, T, -1).transpose(1, 2)


class MatmulConvTranspose1d(torch.nn.Module):
    """The U-Net's upsampling ConvTranspose1d (kernel 2*stride, padding stride/2) as one GEMM
    plus an overlap-add of the two kernel halves (same weights, same output).

    oneDNN's bf16 ConvTranspose1d at these sizes is many times slower than the GEMM (docs/results/model.md);
    torch has no cheaper col2im for 1D, hence the hand-written add."""

    def __init__(self, conv: torch.nn.ConvTranspose1d):
        super().__init__()
        k, s, p = conv.kernel_size[0], conv.stride[0], conv.padding[0]
        if conv.groups != 1 or conv.dilation[0] != 1 or conv.output_padding[0] != 0 or k != 2 * s or 2 * p != s:
            raise ValueError("MatmulConvTranspose1d handles kernel = 2 * stride, padding = stride / 2 only")
        self.stride, self.padding = s, p
        in_ch, out_ch, _ = conv.weight.shape
        # (in, out, k) -> (k*out, in): one product gives every input step's k output contributions
        self.weight = torch.nn.Parameter(
            conv.weight.detach().permute(2, 1, 0).reshape(k * out_ch, in_ch).contiguous(), requires_grad=False
        )
        self.bias = None if conv.bias is None else torch.nn.Parameter(conv.bias.detach().clone(), requires_grad=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        B, C, T = x.shape
        s = self.stride
        z = torch.nn.functional.linear(x.transpose(1, 2).reshape(B * T, C), self.weight)
        z = z.reshape(B, T, 2, s, -1)  # input step i writes output steps i*s + (0..2s-1) - padding
        # overlap-add: output block j (steps j*s .. j*s+s-1, before cropping) = first half of input j + second half of j-1
        full = torch.nn.functional.pad(z[:, :, 0], (0, 0, 0, 0, 0, 1)) + torch.nn.functional.pad(
            z[:, :, 1], (0, 0, 0, 0, 1, 0)
        )
        y = full.reshape(B, (T + 1) * s, -1)[:, self.padding : self.padding + T * s]
        if self.bias is not None:
            y = y + self.bias
        return y.transpose(1, 2)


class FastMish(torch.nn.Module):
    """Mish as x * n / (n + 2) with n = e^x (e^x + 2) (= x tanh(softplus(x))): faster than torch's
    scalar CPU kernel on the U-Net's small tensors (docs/results/model.md). The exponent is clamped at 20,
    where the ratio is 1 to float precision."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        e = torch.clamp(x, max=20.0).exp_()
        n = (e + 2).mul_(e)
        return n.div_(n + 2).mul_(x)


def swap_modules(module: torch.nn.Module, kind: type, replacement) -> int:
    """Replace every module of exactly type ``kind`` under ``module`` by ``replacement(old)``; returns how many."""
    count = 0
    for name, child in module.named_children():
        if type(child) is kind:
            setattr(module, name, replacement(child))
            count += 1
        else:
            count += swap_modules(child, kind, replacement)
    return count


class WholeMapConv3d(torch.nn.Module):
    """An unpadded Conv3d whose kernel covers its whole input (one output voxel) as one matrix-vector
    product on a channels_last_3d input: same weights, same output, several times faster than oneDNN's
    convolution or torch's on channels_last weights (docs/results/model.md)."""

    def __init__(self, conv: torch.nn.Conv3d):
        super().__init__()
        out_ch = conv.out_channels
        # (out, in, kd, kh, kw) -> (out, kd*kh*kw*in): the memory order of a channels_last_3d map
        self.weight = torch.nn.Parameter(
            conv.weight.detach().permute(0, 2, 3, 4, 1).reshape(out_ch, -1).contiguous(), requires_grad=False
        )
        self.bias = None if conv.bias is None else torch.nn.Parameter(conv.bias.detach().clone(), requires_grad=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = torch.nn.functional.linear(x.permute(0, 2, 3, 4, 1).reshape(x.shape[0], -1), self.weight, self.bias)
        return y[:, :, None, None, None]


def onednn_conv3ds(encoder: torch.nn.Sequential, size: int) -> int:
    """Run the Conv3d of ``encoder`` (Conv3d, ReLU and MaxPool3d, input ``size``³) through oneDNN
    (``OneDnnConv3d``), one whose kernel covers its whole input as ``WholeMapConv3d``; returns how many."""
    count = 0
    for i, layer in enumerate(encoder):
        if isinstance(layer, torch.nn.MaxPool3d):
            size = (size - layer.kernel_size) // layer.stride + 1
        elif type(layer) is torch.nn.Conv3d:
            k, pad = layer.kernel_size[0], layer.padding[0]
            whole = pad == 0 and layer.stride == (1, 1, 1) and layer.kernel_size == (size,) * 3
            encoder[i] = WholeMapConv3d(layer) if whole else OneDnnConv3d(layer)
            size = size + 2 * pad - k + 1
            count += 1
    return count


def convs_as_matmuls(module: torch.nn.Module) -> int:
    """Replace every plain Conv1d and the upsampling ConvTranspose1d under ``module`` by GEMM modules."""
    return swap_modules(module, torch.nn.Conv1d, MatmulConv1d) + swap_modules(
        module, torch.nn.ConvTranspose1d, MatmulConvTranspose1d
    )


class Method(torch.nn.Module):
    """Wraps one method of a module so torch.jit.trace can trace it."""

    def __init__(self, module: torch.nn.Module, method: str):
        super().__init__()
        self.module = module
        self.method = method

    def forward(self, *args):
        return getattr(self.module, self.method)(*args)
