"""The layers the zoo's networks share (event_cnn_minimal's ``ConvLayer``, ``UpsampleConvLayer``,
``ResidualBlock``, ``ConvLSTM`` and ``RecurrentConvLayer``, as the V2V authors' ``model/submodules.py``
names them, so parameter names match theirs) and the driver's input padding.

Every network of the zoo zero-pads its voxel grid (N, num_bins, H, W) on the bottom and right to
multiples of :data:`PAD_MULTIPLE` (16, as the V2V authors' training and test driver does before
calling any network: ``model/train_utils.py`` and ``model/train_flow_utils.py``) and crops the
output back, so a released checkpoint gives the authors' outputs on 180 x 240 or 260 x 346 inputs.
"""
from __future__ import annotations

from typing import List, Optional, Sequence, Tuple

import torch
import torch.nn as nn
import torch.nn.functional as F

__all__ = ["PAD_MULTIPLE", "pad_input", "ConvLayer", "UpsampleConvLayer", "ResidualBlock", "ConvLSTM",
           "RecurrentConvLayer", "State", "check_unet_args", "check_voxel", "output_memory_format", "zero_lstm_states"]

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


def check_voxel(voxel: torch.Tensor, num_bins: int) -> None:
    """Raises ``ValueError`` unless ``voxel`` is a batch of voxel grids (N, num_bins, H, W), the
    input every network of the zoo takes."""
    if voxel.ndim != 4 or voxel.shape[1] != num_bins:
        raise ValueError(f"voxel must be (N, {num_bins}, H, W), got {tuple(voxel.shape)}")


def output_memory_format(conv: nn.Conv2d) -> torch.memory_format:
    """The layout ``conv`` gives its outputs: channels-last when its weights are (as
    ``trainer.speed.prepare_model`` makes them), else contiguous (NCHW)."""
    return (torch.channels_last if conv.weight.is_contiguous(memory_format=torch.channels_last)
            else torch.contiguous_format)


def zero_lstm_states(layers: Sequence[RecurrentConvLayer], x: torch.Tensor, requires_grad: bool = False
                     ) -> List[Tuple[torch.Tensor, torch.Tensor]]:
    """The ConvLSTM states a recurrent network starts a sequence from, as tensors: what each
    :class:`ConvLSTM` makes inside for ``state=None`` (zero hidden and cell states), so a
    network called with them gives bit-identically what it gives for ``None`` and a compiled
    network (``speed: fast``) sees one input structure for every step of a sequence.

    ``layers``: the network's :class:`RecurrentConvLayer` chain, layer i halving the sides
    ``i + 1`` times (stride 2 each); ``x`` the padded network input (N, C, H', W'), H' and W'
    multiples of :data:`PAD_MULTIPLE`. Returns one ``(hidden, cell)`` per layer, each
    (N, hidden_size_i, H'/2**(i+1), W'/2**(i+1)), in what a compiled graph guards on as the
    states the network returns: the layout of the convolutions' outputs (channels-last when
    the gate convolution's weights are, as ``trainer.speed.prepare_model`` makes them), the
    dtype of autocast when it is on for ``x``'s device (call this inside the forward's
    autocast region), else ``x``'s, and, with ``requires_grad``, leaves that require grad (as
    the states returned in training do; the parameters' gradients are the same either way).
    """
    if not layers:
        return []
    dev = x.device.type
    dtype = torch.get_autocast_dtype(dev) if torch.is_autocast_enabled(dev) else x.dtype
    fmt = output_memory_format(layers[0].recurrent_block.Gates)
    n, _, h, w = x.shape
    states = []
    for i, layer in enumerate(layers):
        shape = (n, layer.recurrent_block.hidden_size, h // 2 ** (i + 1), w // 2 ** (i + 1))
        states.append(tuple(torch.empty(shape, dtype=dtype, device=x.device, memory_format=fmt).zero_()
                            .requires_grad_(requires_grad) for _ in range(2)))
    return states


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


def check_unet_args(num_bins: int, base_num_channels: int, num_encoders: int, skip_type: str) -> None:
    """The argument checks shared by both UNet variants (E2VID's and EV-FlowNet's).

    Raises:
        ValueError: ``skip_type`` is not ``'sum'`` or ``'concat'``, or a size is < 1.
    """
    if skip_type not in ("sum", "concat"):
        raise ValueError(f"skip_type must be 'sum' or 'concat', got {skip_type!r}")
    if num_encoders < 1 or base_num_channels < 1 or num_bins < 1:
        raise ValueError("num_encoders, base_num_channels and num_bins must be >= 1")

