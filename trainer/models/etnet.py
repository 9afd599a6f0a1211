"""ETNet (Weng et al., "Event-based Video Reconstruction Using Transformer", ICCV 2021) as the V2V
paper retrains it: a recurrent convolutional encoder, multi-scale transformer encoders/decoders
over the bottleneck, and an upsampling decoder with a sigmoid output.

Architecture of the authors' ``model/eitr`` (HYLZ-2019/V2V ``EITR`` / ``mls_tpa``, config
``train_v2v_etnet_10k.yaml``: num_bins 5, norm none), reimplemented with its parameter names:

* ``head``: conv k5 num_bins -> 32, ReLU; ``DownsampleConv.i``: strided conv k5 + ConvLSTM k3,
  32-64-128-256 (outputs at 1/2, 1/4, 1/8).
* Tokens at 1/8: the 256-channel bottleneck per pixel (scale 0), ``split1`` conv k2 s2 of the
  1/4 features (scale 1) and ``split2`` conv k4 s4 of the 1/2 features (scale 2), each plus a
  sinusoidal position table (``position_embedding.pos_table``, (1, 20000, 256) buffer) and
  through ``trans_encoder{0,1,2}`` (3 pre-norm layers, 8 heads, FFN 1024, dropout 0.1).
* ``trans_decoder0`` (tgt = memory = scale 0), ``trans_decoder1`` (scale 1 attending to scale 0),
  ``trans_decoder2`` (scale 2 attending to scale 1): 2 pre-norm layers each (self-attention,
  cross-attention with separate query/memory norms ``norm21``/``norm22``, FFN).
* The mean of the three encoder and three decoder outputs, reshaped to (N, 256, H/8, W/8), goes
  through ``UpsampleConv.i`` (upsample-conv k5, 256-128-64-32) with sum skips from the
  encoders, then ``pred`` (1x1 -> 1) with the head as skip, then a sigmoid.

State-dict keys and shapes equal the authors' (tests/data/zoo_reference.json). Input
(N, num_bins, H, W) float, H and W zero-padded at the bottom and right to multiples of 16 as the
authors' driver pads them (``trainer.models.pad_input``; the attention sees the padded tokens,
as theirs does) and the output cropped back; at most 20000 tokens (H/8 * W/8, padded) per image.
"""
from __future__ import annotations

from typing import List, Optional

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from .layers import ConvLayer, RecurrentConvLayer, UpsampleConvLayer, check_voxel, pad_input, zero_lstm_states

__all__ = ["ETNet", "sinusoid_table"]


def sinusoid_table(n_position: int, d: int) -> torch.Tensor:
    """Transformer position table (Vaswani et al. 2017): float32 (1, n_position, d), sin on even
    and cos on odd channels of pos / 10000^(2*(j//2)/d)."""
    pos = np.arange(n_position, dtype=np.float64)[:, None]
    j = np.arange(d)
    ang = pos / np.power(10000, 2 * (j // 2) / d)
    ang[:, 0::2] = np.sin(ang[:, 0::2])
    ang[:, 1::2] = np.cos(ang[:, 1::2])
    return torch.tensor(ang, dtype=torch.float32)[None]


class _PositionEncoding(nn.Module):
    def __init__(self, d: int, n_position: int = 20000):
        super().__init__()
        self.register_buffer("pos_table", sinusoid_table(n_position, d))


class _EncoderLayer(nn.Module):
    def __init__(self, d, nhead, ff, dropout):
        super().__init__()
        self.self_attn = nn.MultiheadAttention(d, nhead, dropout=dropout)
        self.attn_dropout = nn.Dropout(dropout)
        self.norm1 = nn.LayerNorm(d)
        self.linear1 = nn.Linear(d, ff)
        self.ffn_dropout1 = nn.Dropout(dropout)
        self.linear2 = nn.Linear(ff, d)
        self.ffn_dropout2 = nn.Dropout(dropout)
        self.norm2 = nn.LayerNorm(d)

    def forward(self, x):
        q = self.norm1(x)
        x = x + self.attn_dropout(self.self_attn(q, q, q)[0])
        return x + self.ffn_dropout2(self.linear2(self.ffn_dropout1(F.relu(self.linear1(self.norm2(x))))))


class _DecoderLayer(nn.Module):
    def __init__(self, d, nhead, ff, dropout):
        super().__init__()
        self.self_attn = nn.MultiheadAttention(d, nhead, dropout=dropout)
        self.sattn_dropout = nn.Dropout(dropout)
        self.norm1 = nn.LayerNorm(d)
        self.cross_attn = nn.MultiheadAttention(d, nhead, dropout=dropout)
        self.cattn_dropout = nn.Dropout(dropout)
        self.norm21 = nn.LayerNorm(d)
        self.norm22 = nn.LayerNorm(d)
        self.linear1 = nn.Linear(d, ff)
        self.ffn_dropout1 = nn.Dropout(dropout)
        self.linear2 = nn.Linear(ff, d)
        self.ffn_dropout2 = nn.Dropout(dropout)
        self.norm3 = nn.LayerNorm(d)

    def forward(self, x, memory):
        q = self.norm1(x)
        x = x + self.sattn_dropout(self.self_attn(q, q, q)[0])
        m = self.norm22(memory)
        x = x + self.cattn_dropout(self.cross_attn(self.norm21(x), m, m)[0])
        return x + self.ffn_dropout2(self.linear2(self.ffn_dropout1(F.relu(self.linear1(self.norm3(x))))))


class _Stack(nn.Module):
    """``layers`` of one kind, held as ``<name>.layers.i`` (the authors' nesting)."""

    def __init__(self, layer_cls, n, d, nhead, ff, dropout):
        super().__init__()
        self.layers = nn.ModuleList([layer_cls(d, nhead, ff, dropout) for _ in range(n)])


class _TransformerEncoder(nn.Module):
    def __init__(self, d, nhead, n, ff, dropout):
        super().__init__()
        self.encoder = _Stack(_EncoderLayer, n, d, nhead, ff, dropout)
        for p in self.parameters():
            if p.dim() > 1:
                nn.init.xavier_uniform_(p)

    def forward(self, src, pos):
        x = src + pos
        for layer in self.encoder.layers:
            x = layer(x)
        return x


class _TransformerDecoder(nn.Module):
    def __init__(self, d, nhead, n, ff, dropout):
        super().__init__()
        self.decoder = _Stack(_DecoderLayer, n, d, nhead, ff, dropout)
        for p in self.parameters():
            if p.dim() > 1:
                nn.init.xavier_uniform_(p)

    def forward(self, tgt, memory):
        x = tgt
        for layer in self.decoder.layers:
            x = layer(x, memory)
        return x


class ETNet(nn.Module):
    """ETNet reconstruction network (see the module doc); the authors' fixed sizes.

    Args: num_bins, d_model (the tokens' width), nhead, encoder_layers, decoder_layers,
    dim_feedforward, dropout; declared once, with the authors' sizes as defaults, by
    ``trainer.config.ETNetModel`` (``build_model("etnet", {})``). Reduced values are for CPU demos.

    ``forward(voxel, states=None)``: ``voxel`` float (N, num_bins, H, W); ``states`` None at a
    sequence start or the list returned by the previous call. Returns ``(image (N, 1, H, W) float
    in (0, 1) (sigmoid), states)``. Raises ``ValueError`` for a voxel of the wrong shape or more
    than 20000 tokens.
    """

    def __init__(self, num_bins: int, d_model: int, nhead: int, encoder_layers: int, decoder_layers: int,
                 dim_feedforward: int, dropout: float):
        super().__init__()
        self.num_bins = num_bins
        self.head = ConvLayer(num_bins, 32, 5)
        self.DownsampleConv = nn.ModuleList([RecurrentConvLayer(32, 64, 5), RecurrentConvLayer(64, 128, 5),
                                             RecurrentConvLayer(128, d_model, 5)])
        self.position_embedding = _PositionEncoding(d_model)
        args = (d_model, nhead)
        self.trans_encoder0 = _TransformerEncoder(*args, encoder_layers, dim_feedforward, dropout)
        self.trans_decoder0 = _TransformerDecoder(*args, decoder_layers, dim_feedforward, dropout)
        self.split1 = nn.Conv2d(128, d_model, 2, 2)
        self.trans_encoder1 = _TransformerEncoder(*args, encoder_layers, dim_feedforward, dropout)
        self.trans_decoder1 = _TransformerDecoder(*args, decoder_layers, dim_feedforward, dropout)
        self.split2 = nn.Conv2d(64, d_model, 4, 4)
        self.trans_encoder2 = _TransformerEncoder(*args, encoder_layers, dim_feedforward, dropout)
        self.trans_decoder2 = _TransformerDecoder(*args, decoder_layers, dim_feedforward, dropout)
        self.UpsampleConv = nn.ModuleList([UpsampleConvLayer(d_model, 128, 5), UpsampleConvLayer(128, 64, 5),
                                           UpsampleConvLayer(64, 32, 5)])
        self.pred = ConvLayer(32, 1, 1, relu=False)

    def _tokens(self, feat: torch.Tensor) -> torch.Tensor:
        """(N, C, h, w) -> (h*w, N, C) plus the position table."""
        t = feat.flatten(2).permute(2, 0, 1)
        if t.shape[0] > self.position_embedding.pos_table.shape[1]:
            raise ValueError(f"{t.shape[0]} tokens exceed ETNet's position table of "
                             f"{self.position_embedding.pos_table.shape[1]}")
        return t

    def initial_states(self, voxel: torch.Tensor, requires_grad: bool = False) -> List:
        """The states a sequence starts from, as tensors: zero hidden and cell states of the
        three ``DownsampleConv`` ConvLSTMs ((N, 64 | 128 | d_model, H'/2 | H'/4 | H'/8, ...),
        H' x W' the padded input), so ``forward(voxel, initial_states(voxel))`` is
        bit-identical to ``forward(voxel, None)`` and a compiled network (``speed: fast``) sees
        one input structure for every step of a sequence. Layout, dtype (autocast's when on:
        call it inside the forward's autocast region) and ``requires_grad`` as
        ``trainer.models.layers.zero_lstm_states`` says. Raises ``ValueError`` for a voxel of
        the wrong shape."""
        check_voxel(voxel, self.num_bins)
        return zero_lstm_states(self.DownsampleConv, pad_input(voxel)[0], requires_grad)

    def forward(self, voxel: torch.Tensor, states: Optional[List] = None):
        check_voxel(voxel, self.num_bins)
        x, h, w = pad_input(voxel)
        states = states or [None] * 3
        f = self.head(x)
        head = f
        blocks, new_states = [], []
        for layer, st in zip(self.DownsampleConv, states):
            f, st = layer(f, st)
            blocks.append(f)
            new_states.append(st)
        w0 = self._tokens(blocks[2])
        w1 = self._tokens(self.split1(blocks[1]))
        w2 = self._tokens(self.split2(blocks[0]))
        pos = self.position_embedding.pos_table[0, : w0.shape[0], None, :]
        hs0 = self.trans_encoder0(w0, pos)
        hs1 = self.trans_encoder1(w1, pos)
        hs2 = self.trans_encoder2(w2, pos)
        hc0 = self.trans_decoder0(hs0, hs0)
        hc1 = self.trans_decoder1(hs1, hs0)
        hc2 = self.trans_decoder2(hs2, hs1)
        hs = (hs0 + hs1 + hs2 + hc0 + hc1 + hc2) / 6
        n, c = blocks[2].shape[:2]
        f = hs.permute(1, 2, 0).reshape(n, -1, *blocks[2].shape[2:])
        for i, up in enumerate(self.UpsampleConv):
            f = up(f + blocks[2 - i])
        img = torch.sigmoid(self.pred(f + head))
        return img[..., :h, :w], new_states
