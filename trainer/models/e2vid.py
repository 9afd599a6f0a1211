"""E2VID (recurrent UNet with ConvLSTM encoders) and E2VID++ in PyTorch.

Architecture as configured in the V2V paper's reference training configs (Lou et al.,
NeurIPS 2025), which reuse event_cnn_minimal (Stoffregen et al., ECCV 2020):
``E2VIDRecurrent``: head conv (k5) -> 3 encoders (strided conv k5 + ConvLSTM k3),
channels 32-64-128-256 -> 2 residual blocks -> 3 decoders (bilinear x2 upsample + conv
k5) with *sum* skips -> 1x1 prediction conv, 1 output channel, no final activation;
parameters named as the V2V authors' ``E2VIDRecurrent`` (``unetrecurrent.*``, a ConvLSTM's
gate convolution ``Gates`` inside ``recurrent_block``), so their E2VID checkpoints load.

``trainer.zoo.build_model`` builds these and the other networks of the zoo from a config.
Inputs are voxel grids (N, num_bins, H, W) float, padded as :func:`trainer.models.layers.pad_input`
says and cropped back.
"""
from __future__ import annotations

from typing import List, Optional, Sequence

import torch
import torch.nn as nn

from .layers import (ConvLayer, RecurrentConvLayer, ResidualBlock, State, UpsampleConvLayer, check_unet_args,
                     check_voxel, pad_input, zero_lstm_states)

__all__ = ["E2VIDRecurrent", "E2VIDPlusPlus"]


class _UNetRecurrent(nn.Module):
    """The body of :class:`E2VIDRecurrent` (the authors' ``UNetRecurrent`` on their
    ``BaseUNet``): head conv, recurrent encoders, residual blocks, upsample-conv decoders with
    skips, prediction conv. Submodules are registered in the authors' order (head, residual
    blocks, decoders, prediction, encoders), so parameter order and optimiser states match."""

    def __init__(self, num_bins, base_num_channels, num_encoders, num_residual_blocks, num_output_channels,
                 skip_type, kernel_size, channel_multiplier=2):
        super().__init__()
        check_unet_args(num_bins, base_num_channels, num_encoders, skip_type)
        self.num_bins = num_bins
        self.num_encoders = num_encoders
        self.skip_type = skip_type
        self.enc_in = [base_num_channels * channel_multiplier**i for i in range(num_encoders)]
        self.enc_out = [base_num_channels * channel_multiplier ** (i + 1) for i in range(num_encoders)]
        self.max_ch = self.enc_out[-1]
        self.head = ConvLayer(num_bins, base_num_channels, kernel_size)
        self.resblocks = nn.ModuleList([ResidualBlock(self.max_ch) for _ in range(num_residual_blocks)])
        mult = 2 if skip_type == "concat" else 1
        self.decoders = nn.ModuleList(
            [UpsampleConvLayer(mult * cin, cout, kernel_size)
             for cin, cout in zip(reversed(self.enc_out), reversed(self.enc_in))]
        )
        self.pred = ConvLayer(mult * base_num_channels, num_output_channels, 1, relu=False)
        self.encoders = nn.ModuleList(
            [RecurrentConvLayer(cin, cout, kernel_size) for cin, cout in zip(self.enc_in, self.enc_out)]
        )

    def _skip(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        return x + y if self.skip_type == "sum" else torch.cat([x, y], dim=1)

    def forward(self, voxel: torch.Tensor, states: Optional[List[State]] = None):
        check_voxel(voxel, self.num_bins)
        x, h, w = pad_input(voxel)
        if states is None:
            states = [None] * self.num_encoders
        x = self.head(x)
        head = x
        blocks, new_states = [], []
        for enc, st in zip(self.encoders, states):
            x, st = enc(x, st)
            blocks.append(x)
            new_states.append(st)
        return self._decode(x, blocks, head)[..., :h, :w], new_states

    def _decode(self, x: torch.Tensor, blocks: Sequence[torch.Tensor], head: torch.Tensor) -> torch.Tensor:
        """Residual blocks, decoders with their skip connections, and the prediction layer."""
        for res in self.resblocks:
            x = res(x)
        for i, dec in enumerate(self.decoders):
            x = dec(self._skip(x, blocks[self.num_encoders - i - 1]))
        return self.pred(self._skip(x, head))


#: Top-level parts of this trainer's E2VID state dicts saved without the authors' names (keys
#: without ``unetrecurrent.``, the ConvLSTM's gate convolution ``lstm.gates``).
_OWN_E2VID_PARTS = ("head.", "encoders.", "resblocks.", "decoders.", "pred.")


def _rename_own_e2vid_keys(state_dict, prefix, *_):
    """``load_state_dict`` pre-hook of :class:`E2VIDRecurrent`: keys of a state dict saved with
    this trainer's own names (``encoders.i.lstm.gates.weight``, ...) are renamed in place to the
    authors' (``unetrecurrent.encoders.i.recurrent_block.Gates.weight``, ...), so such
    checkpoints keep loading; the parameters' order is the same, so optimiser states match."""
    for k in list(state_dict):
        rest = k[len(prefix):]
        if k.startswith(prefix) and rest.startswith(_OWN_E2VID_PARTS):
            state_dict[prefix + "unetrecurrent." + rest.replace(".lstm.gates.", ".recurrent_block.Gates.")] = \
                state_dict.pop(k)


class E2VIDRecurrent(nn.Module):
    """E2VID recurrent reconstruction network (Rebecq et al. 2019; event_cnn_minimal and the V2V
    authors' ``E2VIDRecurrent`` / ``UNetRecurrent`` with ConvLSTM encoders).

    The parameters and the reference's sizes (5 bins, base 32, 3 encoders, 'sum' skips, 2
    residual blocks, kernel 5, 1 output) are declared once, by ``trainer.config.E2VIDModel``
    (``build_model("e2vid", {})`` builds them); upsample-conv decoder, no activation.
    State-dict keys and shapes equal the authors' (``unetrecurrent.head.conv2d.weight``, ...,
    ``unetrecurrent.encoders.i.recurrent_block.Gates.weight``; tests/test_trainer_zoo.py), so
    their checkpoints' ``state_dict`` loads with ``load_state_dict``; so do state dicts saved
    with this trainer's own earlier names (``encoders.i.lstm.gates``, renamed on load).

    ``forward(voxel, states)``: ``voxel`` float (N, num_bins, H, W) (signed event counts per
    bin), ``states`` ``None`` or the list returned by the previous call. Returns
    ``(image (N, 1, H, W) float, states)``; the image is in [0, 1] intensity units after
    training but is not clamped. Detach or reset ``states`` between sequences.

    Raises:
        ValueError: bad sizes or skip type at construction; a voxel of another shape in forward.
    """

    def __init__(self, num_bins: int, base_num_channels: int, num_encoders: int, num_residual_blocks: int,
                 num_output_channels: int, skip_type: str, kernel_size: int):
        super().__init__()
        self.num_bins, self.num_encoders = num_bins, num_encoders
        self.unetrecurrent = _UNetRecurrent(num_bins, base_num_channels, num_encoders, num_residual_blocks,
                                            num_output_channels, skip_type, kernel_size)
        self._register_load_state_dict_pre_hook(_rename_own_e2vid_keys)

    def initial_states(self, voxel: torch.Tensor, requires_grad: bool = False) -> List[State]:
        """The states a sequence starts from, as tensors: zero hidden and cell states
        (N, 2**(i+1) * base, H'/2**(i+1), W'/2**(i+1)) for encoder i, H' x W' the padded input,
        so ``forward(voxel, initial_states(voxel))`` is bit-identical to ``forward(voxel, None)``
        and a compiled network (``speed: fast``) sees one input structure for every step of a
        sequence. Layout, dtype (autocast's when on: call it inside the forward's autocast
        region) and ``requires_grad`` as ``trainer.models.layers.zero_lstm_states`` says.
        Raises ``ValueError`` for a voxel of the wrong shape."""
        check_voxel(voxel, self.num_bins)
        return zero_lstm_states(self.unetrecurrent.encoders, pad_input(voxel)[0], requires_grad)

    def forward(self, voxel: torch.Tensor, states: Optional[List[State]] = None):
        return self.unetrecurrent(voxel, states)


class E2VIDPlusPlus(E2VIDRecurrent):
    """E2VID++ (Stoffregen et al., ECCV 2020) as its released checkpoint is built: the authors'
    ``model.model.FlowNet`` / ``UNetFlow`` (V2V ``config/test_e2vid++_original.yaml``), the
    :class:`E2VIDRecurrent` network with a 3-channel prediction convolution whose channel 0 is
    the image and channels 1-2 an optical flow the reconstruction does not use.

    Parameters sit where :class:`E2VIDRecurrent`'s do (``unetrecurrent.*``, ``pred`` 32 -> 3);
    ``trainer.checkpoints`` maps the checkpoint's ``unetflow.*`` keys onto them.

    ``forward(voxel, states)`` as :class:`E2VIDRecurrent`'s; returns ``(image (N, 1, H, W),
    states)``, the image not clamped (the authors' ``output_dict['image']``).
    """

    def __init__(self, **e2vid_params):
        # E2VID's parameters (its model section in trainer.config); the prediction has 3 channels
        super().__init__(**{**e2vid_params, "num_output_channels": 3})

    def forward(self, voxel: torch.Tensor, states: Optional[List[State]] = None):
        out, states = self.unetrecurrent(voxel, states)
        return out[:, :1], states
