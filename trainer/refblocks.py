"""Building blocks named as in the V2V authors' ``model/submodules.py`` (event_cnn_minimal):
a ConvLSTM whose gate convolution is ``Gates`` and a strided conv + ConvLSTM layer whose parts
are ``conv`` and ``recurrent_block``, so that HyperE2VID and ETNet checkpoints of the authors'
code load into :mod:`trainer.hypere2vid` and :mod:`trainer.etnet` with ``load_state_dict``.
"""
from __future__ import annotations

from typing import Optional, Tuple

import torch
import torch.nn as nn

from .models import ConvLayer

__all__ = ["GatesConvLSTM", "RecurrentConvLayer"]

State = Optional[Tuple[torch.Tensor, torch.Tensor]]


class GatesConvLSTM(nn.Module):
    """Convolutional LSTM cell (Shi et al. 2015), gate convolution named ``Gates``.

    ``forward(x (N, input_size, H, W) float, state None | (hidden, cell) each
    (N, hidden_size, H, W))`` -> ``(hidden, cell)``; a ``None`` state is zeros.
    Gate order in the convolution's output channels: input, remember, output, cell.
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
        i, r, o, c = self.Gates(torch.cat([x, prev_hidden], dim=1)).chunk(4, dim=1)
        cell = torch.sigmoid(r) * prev_cell + torch.sigmoid(i) * torch.tanh(c)
        return torch.sigmoid(o) * torch.tanh(cell), cell


class RecurrentConvLayer(nn.Module):
    """Strided ``conv`` (ConvLayer + ReLU, stride 2, padding k//2) then a ``recurrent_block``
    ConvLSTM (kernel 3) on its output. ``forward(x, state)`` -> ``(hidden, (hidden, cell))``."""

    def __init__(self, cin: int, cout: int, kernel_size: int):
        super().__init__()
        self.conv = ConvLayer(cin, cout, kernel_size, stride=2)
        self.recurrent_block = GatesConvLSTM(cout, cout, 3)

    def forward(self, x: torch.Tensor, state: State):
        state = self.recurrent_block(self.conv(x), state)
        return state[0], state
