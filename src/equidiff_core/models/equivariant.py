"""EquiDiff (Vo) noise predictor in escnn: C_N-equivariant in observation and action.

    voxels (4 trivial fields) --8 x R3Conv + ReLU, 4 max-pools--> F regular fields at 1^3
    [voxel fields, gripper state (rho1^4 + rho0^2)] --equivariant Linear--> H regular fields
        (the official code's enc_out; the legacy layout adds a ReLU)
    noisy action step (action irreps) --equivariant Linear + ReLU--> A regular fields
    U-Net(A channels, cond H) applied with shared weights to each of the N group elements
    --equivariant Linear--> epsilon (action irreps)

A regular field's N channels are indexed by group element and g permutes them cyclically, so
running the same U-Net on each element's slice commutes with g. C4 is exact on the voxel grid
(rot90 permutes voxels); the odd elements of C8 are only approximate there (the 3^3 kernels
are sampled on a grid that 45 deg does not map to itself).
"""

from __future__ import annotations

import torch
from escnn import gspaces
from escnn import nn as enn

from ..policy.presets import PolicyPreset
from . import action_space
from .plain import EquiNoiseCore, PlainEquiNoisePredictor, encoder_layer_specs, obs_embedding_relu
from .sparse_stage import conv_pool_occupied, is_conv_pool_stage, sparse_first_stage_enabled


def irreps_type(gspace, freqs: tuple[int, ...], repeat: int = 1) -> list:
    G = gspace.fibergroup
    return [G.irrep(k) for k in freqs] * repeat


class EquiNoisePredictor(EquiNoiseCore):
    def __init__(self, preset: PolicyPreset, action_freqs: tuple[int, ...]):
        super().__init__()
        self._init_common(preset, action_freqs)
        N = preset.group_order
        self.gspace = gspaces.rot2dOnR3(n=N)
        self.point_space = gspaces.no_base_space(self.gspace.fibergroup)
        gs, gp = self.gspace, self.point_space

        # --- voxel encoder
        channels = [preset.voxel_channels] + [f * N for f in preset.encoder_channels]
        field_counts = [preset.voxel_channels] + list(preset.encoder_channels)
        ftype = enn.FieldType(gs, preset.voxel_channels * [gs.trivial_repr])
        self.in_type = ftype
        layers = []
        conv_i = 0
        for spec in encoder_layer_specs(preset, channels):
            if spec[0] == "conv":
                conv_i += 1
                _, _, _, k, pad = spec
                out = enn.FieldType(gs, field_counts[conv_i] * [gs.regular_repr])
                layers.append(enn.R3Conv(ftype, out, kernel_size=k, padding=pad))
                ftype = out
            elif spec[0] == "relu":
                layers.append(enn.ReLU(ftype, inplace=True))
            else:
                layers.append(enn.PointwiseMaxPool3D(ftype, spec[1]))
        self.encoder = enn.SequentialModule(*layers)

        # --- observation embedding: voxel fields of every obs step, then the gripper states
        To = preset.n_obs_steps
        obs_reps = To * preset.encoder_channels[-1] * [gp.regular_repr] + irreps_type(gp, action_space.EE_FREQS, To)
        self.obs_type = enn.FieldType(gp, obs_reps)
        hidden = enn.FieldType(gp, preset.obs_hidden * [gp.regular_repr])
        obs_layers = [enn.Linear(self.obs_type, hidden)] + (
            [enn.ReLU(hidden, inplace=True)] if obs_embedding_relu(preset) else []
        )
        self.obs_linear = enn.SequentialModule(*obs_layers)

        # --- action embedding and decoder
        self.action_type = enn.FieldType(gp, irreps_type(gp, self.action_freqs))
        a_hidden = enn.FieldType(gp, preset.action_hidden * [gp.regular_repr])
        self.action_enc = enn.SequentialModule(enn.Linear(self.action_type, a_hidden), enn.ReLU(a_hidden, inplace=True))
        self.action_dec = enn.Linear(a_hidden, self.action_type)
        self._a_hidden_type = a_hidden

    def _encode_voxels(self, x):
        layers = list(self.encoder.children())
        if not (
            sparse_first_stage_enabled(x)
            and isinstance(layers[0], enn.R3Conv)
            and isinstance(layers[1], enn.PointwiseMaxPool3D)  # the official layout, its pool before the ReLU
            and is_conv_pool_stage(*layers[:2])
        ):
            return self.encoder(enn.GeometricTensor(x, self.in_type)).tensor
        conv, pool = layers[:2]
        # escnn's own filter: expanded from the weights while training, the one it cached in eval mode
        weight, bias = conv.expand_parameters() if conv.training else (conv.filter, conv.expanded_bias)
        h = enn.GeometricTensor(conv_pool_occupied(x, weight, bias), pool.out_type)
        for layer in layers[2:]:
            h = layer(h)
        return h.tensor

    def _obs_linear(self, x):
        return self.obs_linear(enn.GeometricTensor(x, self.obs_type)).tensor

    def _action_enc(self, x):
        return self.action_enc(enn.GeometricTensor(x, self.action_type)).tensor

    def _action_dec(self, x):
        return self.action_dec(enn.GeometricTensor(x, self._a_hidden_type)).tensor

    @torch.no_grad()
    def export_plain(self) -> PlainEquiNoisePredictor:
        """The same function as plain torch modules (escnn's own export of each layer)."""
        was_training = self.training
        self.eval()  # escnn expands its filters in eval mode; export uses them
        plain = PlainEquiNoisePredictor(self.preset, self.action_freqs)
        plain.encoder.load_state_dict(self.encoder.export().state_dict())
        plain.obs_linear.load_state_dict(self.obs_linear.export().state_dict())
        plain.action_enc.load_state_dict(self.action_enc.export().state_dict())
        plain.action_dec.load_state_dict(self.action_dec.export().state_dict())
        plain.unet.load_state_dict(self.unet.state_dict())
        self.train(was_training)
        return plain.eval().to(next(self.parameters()).device)
