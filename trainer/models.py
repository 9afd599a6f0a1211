"""E2VID (recurrent UNet with ConvLSTM encoders) and EVFlowNet (UNet) in PyTorch.

Architectures as configured in the V2V paper's reference training configs (Lou et al.,
NeurIPS 2025), which reuse event_cnn_minimal (Stoffregen et al., ECCV 2020):

* ``E2VIDRecurrent``: head conv (k5) -> 3 encoders (strided conv k5 + ConvLSTM k3),
  channels 32-64-128-256 -> 2 residual blocks -> 3 decoders (bilinear x2 upsample + conv
  k5) with *sum* skips -> 1x1 prediction conv, 1 output channel, no final activation;
  parameters named as the V2V authors' ``E2VIDRecurrent`` (``unetrecurrent.*``, a ConvLSTM's
  gate convolution ``Gates`` inside ``recurrent_block``), so their E2VID checkpoints load.
* ``EVFlowNet``: the reference's ``UNet`` with no head layer: 4 strided-conv encoders
  (5 -> 64 -> 128 -> 256 -> 512, k3) -> 2 residual blocks -> 4 upsample-conv decoders with
  *concat* skips (to 256, 128, 64, 32) -> 1x1 prediction conv 32 -> 2 (optical flow in
  pixels, channel 0 = x/u, 1 = y/v), parameters named as the reference's.

``trainer.zoo.build_model`` builds these and the other networks of the zoo from a config.
Inputs are voxel grids (N, num_bins, H, W) float; H and W need not be multiples of 16:
every network of the zoo zero-pads its input on the bottom and right to multiples of
``PAD_MULTIPLE`` (16, as the V2V authors' training and test driver does before calling any
network: ``model/train_utils.py`` and ``model/train_flow_utils.py``) and crops the output back,
so a released checkpoint gives the authors' outputs on 180 x 240 or 260 x 346 inputs.
"""
from __future__ import annotations

from typing import List, Optional, Sequence, Tuple

import torch
import torch.nn as nn
import torch.nn.functional as F

__all__ = ["PAD_MULTIPLE", "pad_input", "ConvLSTM", "RecurrentConvLayer", "E2VIDRecurrent", "E2VIDPlusPlus", "UNet",
           "EVFlowNet"]

State = Optional[Tuple[torch.Tensor, torch.Tensor]]


class ConvLayer(nn.Module):
    """Conv2d + optional ReLU (event_cnn_minimal ``ConvLayer`` with norm=None; the convolution
    is named ``conv2d`` as there, so parameter names match the reference's)."""

    def __init__(self, cin: int, cout: int, kernel_size: int, stride: int = 1, relu: bool = True):
        super().__init__()
        self.conv2d = nn.Conv2d(cin, cout, kernel_size, stride, padding=kernel_size // 2, bias=True)
        self.relu = relu

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.conv2d(x)
        return F.relu(x) if self.relu else x


class UpsampleConvLayer(nn.Module):
    """Bilinear x2 upsampling followed by Conv2d + ReLU (``use_upsample_conv=True``)."""

    def __init__(self, cin: int, cout: int, kernel_size: int):
        super().__init__()
        self.conv2d = nn.Conv2d(cin, cout, kernel_size, 1, padding=kernel_size // 2, bias=True)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = F.interpolate(x, scale_factor=2, mode="bilinear", align_corners=False)
        return F.relu(self.conv2d(x))


class ResidualBlock(nn.Module):
    """conv3-ReLU-conv3 + identity, then ReLU (norm=None)."""

    def __init__(self, ch: int):
        super().__init__()
        self.conv1 = nn.Conv2d(ch, ch, 3, 1, 1, bias=True)
        self.conv2 = nn.Conv2d(ch, ch, 3, 1, 1, bias=True)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = F.relu(self.conv1(x))
        out = self.conv2(out)
        return F.relu(out + x)


class ConvLSTM(nn.Module):
    """Convolutional LSTM cell (Shi et al. 2015; event_cnn_minimal's and the V2V authors'
    ``ConvLSTM``, gate convolution named ``Gates`` as theirs).

    Args:
        input_size: channels of the input x.
        hidden_size: channels of the hidden and cell states.
        kernel_size: odd kernel of the gate convolution.

    ``forward(x (N, input_size, H, W), state)`` with ``state`` ``None`` (zeros) or
    ``(hidden, cell)`` each (N, hidden_size, H, W); returns ``(hidden, cell)``. Gate order in
    the convolution's output channels: input, remember, output, cell.
    """

    def __init__(self, input_size: int, hidden_size: int, kernel_size: int = 3):
        super().__init__()
        self.hidden_size = hidden_size
        self.Gates = nn.Conv2d(input_size + hidden_size, 4 * hidden_size, kernel_size, padding=kernel_size // 2)

    def forward(self, x: torch.Tensor, state: State = None) -> Tuple[torch.Tensor, torch.Tensor]:
        if state is None:
            shape = (x.shape[0], self.hidden_size, x.shape[2], x.shape[3])
            state = (x.new_zeros(shape), x.new_zeros(shape))
        prev_hidden, prev_cell = state
        gates = self.Gates(torch.cat([x, prev_hidden], dim=1))
        in_gate, remember_gate, out_gate, cell_gate = gates.chunk(4, dim=1)
        cell = torch.sigmoid(remember_gate) * prev_cell + torch.sigmoid(in_gate) * torch.tanh(cell_gate)
        hidden = torch.sigmoid(out_gate) * torch.tanh(cell)
        return hidden, cell


class RecurrentConvLayer(nn.Module):
    """Strided ``conv`` (ConvLayer + ReLU, stride 2, padding k//2) then a ``recurrent_block``
    ConvLSTM (kernel 3) on its output, named as the authors' (E2VID, HyperE2VID and ETNet use
    it). ``forward(x, state)`` -> ``(hidden, (hidden, cell))``."""

    def __init__(self, cin: int, cout: int, kernel_size: int):
        super().__init__()
        self.conv = ConvLayer(cin, cout, kernel_size, stride=2)
        self.recurrent_block = ConvLSTM(cout, cout, 3)

    def forward(self, x: torch.Tensor, state: State) -> Tuple[torch.Tensor, Tuple[torch.Tensor, torch.Tensor]]:
        state = self.recurrent_block(self.conv(x), state)
        return state[0], state


#: Input sides are zero-padded to multiples of this (bottom and right) before any network of the
#: zoo runs: the V2V authors' driver's ``PAD = 16`` (``model/train_utils.py``
#: ``forward_sequence``, ``model/train_flow_utils.py`` ``forward_sequence_evflow``).
PAD_MULTIPLE = 16


def pad_input(x: torch.Tensor) -> Tuple[torch.Tensor, int, int]:
    """Zero-pad ``x`` (..., H, W) at the bottom and right to sides that are multiples of
    :data:`PAD_MULTIPLE`, as the V2V authors' driver pads voxel grids (and HyperE2VID's
    ground-truth frames) before the network. Returns ``(padded, H, W)``; the caller crops the
    output back with ``[..., :H, :W]``."""
    return _pad_to_multiple(x, PAD_MULTIPLE)


def _pad_to_multiple(x: torch.Tensor, m: int) -> Tuple[torch.Tensor, int, int]:
    h, w = x.shape[-2:]
    ph, pw = (-h) % m, (-w) % m
    if ph or pw:
        x = F.pad(x, (0, pw, 0, ph))
    return x, h, w


def _check_unet_args(num_bins: int, base_num_channels: int, num_encoders: int, skip_type: str) -> None:
    """The argument checks shared by both UNet variants."""
    if skip_type not in ("sum", "concat"):
        raise ValueError(f"skip_type must be 'sum' or 'concat', got {skip_type!r}")
    if num_encoders < 1 or base_num_channels < 1 or num_bins < 1:
        raise ValueError("num_encoders, base_num_channels and num_bins must be >= 1")


class _UNetBase(nn.Module):
    def __init__(self, num_bins, base_num_channels, num_encoders, num_residual_blocks,
                 num_output_channels, skip_type, kernel_size, channel_multiplier=2):
        super().__init__()
        _check_unet_args(num_bins, base_num_channels, num_encoders, skip_type)
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

    def _skip(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        return x + y if self.skip_type == "sum" else torch.cat([x, y], dim=1)

    def _decode(self, x: torch.Tensor, blocks: Sequence[torch.Tensor], head: torch.Tensor) -> torch.Tensor:
        for res in self.resblocks:
            x = res(x)
        for i, dec in enumerate(self.decoders):
            x = dec(self._skip(x, blocks[self.num_encoders - i - 1]))
        return self.pred(self._skip(x, head))


class _UNetRecurrent(_UNetBase):
    """The body of :class:`E2VIDRecurrent` (the authors' ``UNetRecurrent``)."""

    def __init__(self, num_bins, base_num_channels, num_encoders, num_residual_blocks, num_output_channels,
                 skip_type, kernel_size):
        super().__init__(num_bins, base_num_channels, num_encoders, num_residual_blocks,
                         num_output_channels, skip_type, kernel_size)
        self.encoders = nn.ModuleList(
            [RecurrentConvLayer(cin, cout, kernel_size) for cin, cout in zip(self.enc_in, self.enc_out)]
        )

    def forward(self, voxel: torch.Tensor, states: Optional[List[State]] = None):
        if voxel.ndim != 4 or voxel.shape[1] != self.num_bins:
            raise ValueError(f"voxel must be (N, {self.num_bins}, H, W), got {tuple(voxel.shape)}")
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
        img = self._decode(x, blocks, head)
        return img[..., :h, :w], new_states


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


class UNet(nn.Module):
    """The reference's feed-forward UNet (event_cnn_minimal / V2V ``model/unet.py`` ``UNet``):
    *no head layer*. The first encoder takes the voxel's ``num_bins`` channels directly
    (strided conv ``num_bins -> 2 * base``), every encoder output is a skip, and the
    prediction is a 1x1 conv from the last decoder's ``base`` channels (no head skip).

    Parameter names and shapes (paper config, 5 bins, base 32, 4 encoders, concat, k3):
    ``encoders.i.conv2d`` 5->64, 64->128, 128->256, 256->512 (stride 2); ``resblocks.j.conv1/
    conv2`` 512->512; ``decoders.i.conv2d`` 1024->256, 512->128, 256->64, 128->32 (bilinear x2
    then conv); ``pred.conv2d`` 32->2 (1x1, no activation); every conv has a bias.
    ``forward(x (N, num_bins, H, W))`` with H, W multiples of 2**num_encoders ->
    (N, num_output_channels, H, W).
    """

    def __init__(self, num_bins: int, base_num_channels: int, num_encoders: int, num_residual_blocks: int,
                 num_output_channels: int, skip_type: str, kernel_size: int, channel_multiplier: int = 2):
        super().__init__()
        _check_unet_args(num_bins, base_num_channels, num_encoders, skip_type)
        self.num_encoders = num_encoders
        self.skip_type = skip_type
        enc_in = [base_num_channels * channel_multiplier**i for i in range(num_encoders)]
        enc_out = [base_num_channels * channel_multiplier ** (i + 1) for i in range(num_encoders)]
        enc_in[0] = num_bins  # no head: the first encoder reads the voxel
        self.encoders = nn.ModuleList(
            [ConvLayer(cin, cout, kernel_size, stride=2) for cin, cout in zip(enc_in, enc_out)])
        self.resblocks = nn.ModuleList([ResidualBlock(enc_out[-1]) for _ in range(num_residual_blocks)])
        mult = 2 if skip_type == "concat" else 1
        dec_out = [base_num_channels * channel_multiplier**i for i in range(num_encoders)]
        self.decoders = nn.ModuleList(
            [UpsampleConvLayer(mult * cin, cout, kernel_size) for cin, cout in zip(reversed(enc_out), reversed(dec_out))])
        self.pred = ConvLayer(base_num_channels, num_output_channels, 1, relu=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        blocks = []
        for enc in self.encoders:
            x = enc(x)
            blocks.append(x)
        for res in self.resblocks:
            x = res(x)
        for i, dec in enumerate(self.decoders):
            skip = blocks[self.num_encoders - i - 1]
            x = dec(x + skip if self.skip_type == "sum" else torch.cat([x, skip], dim=1))
        return self.pred(x)


class EVFlowNet(nn.Module):
    """EV-FlowNet (Zhu et al. 2018) as event_cnn_minimal's / the V2V reference's
    ``EVFlowNet``: a :class:`UNet` (no head layer) held as ``self.unet``, so its
    ``state_dict()`` keys are the reference's (``unet.encoders.0.conv2d.weight``, ...) and
    reference checkpoints' ``state_dict`` load with ``load_state_dict`` as they are.

    The parameters and the reference's sizes (5 bins, base 32, 4 encoders, 'concat' skips, 2
    residual blocks, kernel 3, 2 outputs) are declared once, by ``trainer.config.EvFlowModel``
    (``build_model("evflow", {})`` builds them); upsample-conv decoder.

    ``forward(voxel)``: float (N, num_bins, H, W) -> flow float (N, 2, H, W) in pixels over
    the voxel's time span (channel 0 = x/u, 1 = y/v). H, W need not be multiples of
    16 (zero-padded bottom/right, output cropped back). Raises ``ValueError``
    for a voxel of the wrong shape.
    """

    def __init__(self, num_bins: int, base_num_channels: int, num_encoders: int, num_residual_blocks: int,
                 num_output_channels: int, skip_type: str, kernel_size: int):
        super().__init__()
        self.num_bins = num_bins
        self.num_encoders = num_encoders
        self.unet = UNet(num_bins, base_num_channels, num_encoders, num_residual_blocks, num_output_channels,
                         skip_type, kernel_size)

    def forward(self, voxel: torch.Tensor) -> torch.Tensor:
        if voxel.ndim != 4 or voxel.shape[1] != self.num_bins:
            raise ValueError(f"voxel must be (N, {self.num_bins}, H, W), got {tuple(voxel.shape)}")
        x, h, w = pad_input(voxel)
        return self.unet(x)[..., :h, :w]
