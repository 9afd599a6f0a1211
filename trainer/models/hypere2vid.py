"""HyperE2VID (Ercan et al., IEEE TIP 2024) as the V2V paper retrains it: E2VID's recurrent
UNet whose first decoder convolves with per-pixel dynamic filters generated from a context of
the voxel grid and the previous reconstruction.

Architecture of the authors' ``model/hyper_model.py`` (HYLZ-2019/V2V, config
``train_v2v_hyper_10k.yaml``), reimplemented:

* ``unetrecurrent.head``: conv k5, num_bins -> 32, ReLU.
* ``unetrecurrent.encoders.i``: strided conv k5 + ConvLSTM k3 (32-64-128-256).
* ``unetrecurrent.resblocks.j``: 2 residual blocks at 256 channels.
* ``unetrecurrent.decoders.0``: the dynamic decoder: bilinear x2 upsample, then per-pixel
  filters. Context = concat(voxel, previous reconstruction) bilinearly downsampled x1/4,
  conv k3 -> 32 (``context_fusion.conv``); ``dynamic_atom_generation.bases_net`` (conv k3 ->
  64, BN, tanh, conv k3 -> atoms x bases, BN, tanh) gives per pixel the coefficients of 6
  atoms over 12 multiscale Fourier-Bessel bases (``bases``, a 12 x 25 buffer); the atoms
  unfold the upsampled features (k5) and ``dynamic_conv.compositional_coefficients`` (1x1)
  mixes the (channels x atoms) responses, plus ``dynamic_conv.bias``, then ReLU.
  The context is at 1/4 of the input resolution and the features at 1/4 after the first
  upsample of a 3-encoder UNet, so the two grids agree.
* ``unetrecurrent.decoders.1..2``: upsample-conv k5; ``unetrecurrent.pred``: conv 1x1 -> 1,
  no final activation. Skips are sums.

State-dict keys and shapes equal the authors' (tests/data/zoo_reference.json), so their
checkpoints' ``state_dict`` load as they are. Input voxel grids (N, num_bins, H, W) float;
H and W are zero-padded at the bottom and right to multiples of 16 as the authors' driver
pads them (``trainer.models.pad_input``; the ground-truth frame of the curriculum too) and the
output is cropped back; the previous reconstruction in the state keeps the padded size.
"""
from __future__ import annotations

from functools import lru_cache
from typing import List, Optional, Tuple, Union

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from .layers import (ConvLayer, RecurrentConvLayer, ResidualBlock, UpsampleConvLayer, check_voxel,
                     output_memory_format, pad_input, zero_lstm_states)

__all__ = ["fourier_bessel_bases", "HyperE2VID"]


def _bessel_zero_table(kmax: int, limit: float) -> np.ndarray:
    """Rows (k, q, z_kq, z_k(q+1)) of the zeros z of J_k, k = 0..kmax, for every q whose next
    zero is <= ``limit`` (the same rows the authors' ``bessel.npy`` table gives under that filter)."""
    from scipy import special

    rows = []
    for k in range(kmax + 1):
        n = 2
        while special.jn_zeros(k, n)[-1] <= limit:
            n += 1
        z = special.jn_zeros(k, n)
        rows += [(k, q + 1, z[q], z[q + 1]) for q in range(n - 1) if z[q + 1] <= limit]
    return np.array(rows, dtype=np.float64).reshape(-1, 4)


def _fb_bases_one_scale(l1: int) -> np.ndarray:
    """Normalised Fourier-Bessel bases on a (2*l1+1)^2 grid, columns ordered by radial
    frequency: ((2*l1+1)^2, n) float. Qiu et al., "DCFNet" (ICML 2018), calculate_FB_bases."""
    from scipy import special

    L, R = l1 + 1, l1 + 0.5
    factor = 2.0 if l1 < 2 else 1.5
    xx, yy = np.meshgrid(np.arange(-L, L + 1), np.arange(-L, L + 1))
    xx, yy = xx / R, yy / R
    theta = np.arctan2(xx.ravel(), yy.ravel())
    rho = np.hypot(xx.ravel(), yy.ravel())
    table = _bessel_zero_table(15, np.pi * R * factor)
    table = table[np.argsort(table[:, 2], kind="stable")]
    psi = []
    for k, _q, z, _z1 in table:
        phi = special.jv(k, rho * z) / abs(special.jv(k + 1, z))
        phi[rho >= 1] = 0
        if k == 0:
            psi.append(phi)
        else:
            psi += [phi * np.cos(k * theta) * np.sqrt(2), phi * np.sin(k * theta) * np.sqrt(2)]
    psi = np.array(psi)[: (2 * l1 + 1) ** 2 - 1]
    n = len(psi)
    p = psi.reshape(n, 2 * L + 1, 2 * L + 1)[:, 1:-1, 1:-1].reshape(n, -1).T
    return p / np.sqrt((p ** 2).sum(0).mean())


@lru_cache(maxsize=None)
def _fb_bases_cached(kernel_size: int, num_bases: int) -> Tuple[Tuple[float, ...], ...]:
    out = []
    for i in range(kernel_size // 2):
        ks = 2 * (i + 1) + 1
        b = _fb_bases_one_scale(i + 1).T.reshape(-1, ks, ks)[:num_bases]
        pad = kernel_size // 2 - (i + 1)
        b = np.pad(b, ((0, 0), (pad, pad), (pad, pad)))
        out += [tuple(row) for row in b.reshape(num_bases, kernel_size * kernel_size)]
    return tuple(out)


def fourier_bessel_bases(kernel_size: int = 5, num_bases: int = 6) -> torch.Tensor:
    """Multiscale Fourier-Bessel bases of HyperE2VID's dynamic atoms: for each scale
    s = 1..kernel_size//2, the first ``num_bases`` bases on a (2s+1)^2 grid zero-padded to
    kernel_size^2. Returns float32 (kernel_size//2 * num_bases, kernel_size^2); for the
    default (5, 6): (12, 25). Raises ``ValueError`` for an even or < 3 kernel size."""
    if kernel_size < 3 or kernel_size % 2 == 0:
        raise ValueError(f"kernel_size must be odd and >= 3, got {kernel_size}")
    return torch.tensor(_fb_bases_cached(kernel_size, num_bases), dtype=torch.float32)


class ConvolutionalContextFusion(nn.Module):
    """concat(voxel, previous reconstruction) -> bilinear x1/``downsample`` -> conv k3 (``conv``)."""

    def __init__(self, cin: int, cout: int, downsample: int = 4):
        super().__init__()
        self.scale = 1.0 / downsample
        self.conv = nn.Conv2d(cin, cout, 3, padding=1)

    def forward(self, voxel: torch.Tensor, prev_rec: torch.Tensor) -> torch.Tensor:
        ctx = F.interpolate(torch.cat([voxel, prev_rec], 1), scale_factor=self.scale, mode="bilinear",
                            align_corners=False)
        return self.conv(ctx)


class DynamicAtomGeneration(nn.Module):
    """Per-pixel atoms from the context: ``bases_net`` gives (num_atoms x num_bases) coefficients
    per pixel, combined with the ``bases`` buffer into (N, num_atoms, k*k, H, W) atoms."""

    def __init__(self, kernel_size: int, num_atoms: int = 6, num_bases: int = 6, cin: int = 32, hidden: int = 64):
        super().__init__()
        self.num_atoms = num_atoms
        self.register_buffer("bases", fourier_bessel_bases(kernel_size, num_bases))
        n = num_atoms * self.bases.shape[0]
        self.bases_net = nn.Sequential(nn.Conv2d(cin, hidden, 3, padding=1), nn.BatchNorm2d(hidden), nn.Tanh(),
                                       nn.Conv2d(hidden, n, 3, padding=1), nn.BatchNorm2d(n), nn.Tanh())

    def forward(self, context: torch.Tensor) -> torch.Tensor:
        n, _, h, w = context.shape
        coeff = self.bases_net(context).reshape(n, self.num_atoms, self.bases.shape[0], h, w)
        return torch.einsum("nakhw,kl->nalhw", coeff, self.bases)


class DynamicConv(nn.Module):
    """Convolution of (N, cin, H, W) features with per-pixel atoms (N, A, k*k, H, W), then a
    learned 1x1 mixing (``compositional_coefficients`` (cout, cin*A, 1, 1)) plus ``bias``."""

    def __init__(self, cin: int, cout: int, kernel_size: int, num_atoms: int = 6):
        super().__init__()
        self.cin, self.k, self.num_atoms = cin, kernel_size, num_atoms
        self.compositional_coefficients = nn.Parameter(torch.empty(cout, cin * num_atoms, 1, 1))
        self.bias = nn.Parameter(torch.zeros(cout))
        nn.init.kaiming_normal_(self.compositional_coefficients, mode="fan_out", nonlinearity="relu")

    def forward(self, x: torch.Tensor, atoms: torch.Tensor) -> torch.Tensor:
        n, _, h, w = x.shape
        cols = F.unfold(x, self.k, padding=self.k // 2).view(n, self.cin, self.k * self.k, h, w)
        mixed = torch.einsum("nalhw,nclhw->ncahw", atoms, cols).reshape(n, self.cin * self.num_atoms, h, w)
        return F.conv2d(mixed, self.compositional_coefficients, self.bias)


class DynamicUpsampleLayer(nn.Module):
    """Bilinear x2 upsample, dynamic per-pixel convolution, ReLU (HyperE2VID's first decoder)."""

    def __init__(self, cin: int, cout: int, kernel_size: int, context_in: int, context_ch: int = 32,
                 num_atoms: int = 6):
        super().__init__()
        self.context_fusion = ConvolutionalContextFusion(context_in, context_ch)
        self.dynamic_atom_generation = DynamicAtomGeneration(kernel_size, num_atoms, 6, context_ch, 64)
        self.dynamic_conv = DynamicConv(cin, cout, kernel_size, num_atoms)

    def forward(self, x: torch.Tensor, voxel: torch.Tensor, prev_rec: torch.Tensor) -> torch.Tensor:
        x = F.interpolate(x, scale_factor=2, mode="bilinear", align_corners=False)
        atoms = self.dynamic_atom_generation(self.context_fusion(voxel, prev_rec))
        return F.relu(self.dynamic_conv(x, atoms))


class _UNetRecurrentDynamic(nn.Module):
    def __init__(self, num_bins, base_num_channels, num_encoders, num_residual_blocks, kernel_size):
        super().__init__()
        enc_in = [base_num_channels * 2**i for i in range(num_encoders)]
        enc_out = [base_num_channels * 2 ** (i + 1) for i in range(num_encoders)]
        self.head = ConvLayer(num_bins, base_num_channels, kernel_size)
        self.encoders = nn.ModuleList([RecurrentConvLayer(i, o, kernel_size) for i, o in zip(enc_in, enc_out)])
        self.resblocks = nn.ModuleList([ResidualBlock(enc_out[-1]) for _ in range(num_residual_blocks)])
        decs = []
        for idx, (cin, cout) in enumerate(zip(reversed(enc_out), reversed(enc_in))):
            decs.append(DynamicUpsampleLayer(cin, cout, kernel_size, num_bins + 1) if idx == 0
                        else UpsampleConvLayer(cin, cout, kernel_size))
        self.decoders = nn.ModuleList(decs)
        self.pred = ConvLayer(base_num_channels, 1, 1, relu=False)


class HyperE2VID(nn.Module):
    """HyperE2VID reconstruction network (see the module doc).

    Args: num_bins, base_num_channels, num_encoders (3 only), num_residual_blocks, kernel_size
    (also the dynamic filters' size); declared once, with the authors' ``unet_kwargs`` as
    defaults, by ``trainer.config.HyperE2VIDModel`` (``build_model("hypere2vid", {})``).
    Skips are sums, decoders upsample-conv, norm none, one output channel.

    ``forward(voxel, states=None, gt_image=None, beta=0.0)``: ``voxel`` float (N, num_bins, H, W);
    ``states`` None (sequence start: zero LSTM states and a zero previous reconstruction) or the
    value returned by the previous call. ``gt_image`` (N, 1, H, W) and ``beta`` in [0, 1] are the
    training curriculum: the context sees ``(1 - beta) * previous reconstruction + beta * gt_image``
    (the authors' ``HyperE2VID.forward``). ``beta`` is a float (no blend at 0), or a 0-dim float
    tensor on the voxel's device (``speed: fast``: the same graph for every value; exactly the
    reconstruction at 0 and exactly ``gt_image`` at 1, as the float; between, the blend's
    ``1 - beta`` is rounded to the tensor's dtype). Returns ``(image (N, 1, H, W) float, states)``; the
    previous reconstruction kept in ``states`` is detached, as in the authors' code.

    Raises ``ValueError`` for a voxel of the wrong shape.
    """

    def __init__(self, num_bins: int, base_num_channels: int, num_encoders: int, num_residual_blocks: int,
                 kernel_size: int):
        super().__init__()
        # the context grid (1/4 of the input) must equal the first decoder's (1/2**(num_encoders-1))
        if num_encoders != 3:
            raise ValueError(f"HyperE2VID's dynamic decoder needs num_encoders == 3, got {num_encoders}")
        self.num_bins = num_bins
        self.num_encoders = num_encoders
        self.unetrecurrent = _UNetRecurrentDynamic(num_bins, base_num_channels, num_encoders,
                                                   num_residual_blocks, kernel_size)

    def initial_states(self, voxel: torch.Tensor, requires_grad: bool = False
                       ) -> Tuple[List[Tuple[torch.Tensor, torch.Tensor]], torch.Tensor]:
        """The state a sequence starts from, as tensors: what ``forward(voxel, None)`` makes
        inside (zero LSTM hidden and cell states, (N, 2**(i+1) * base, H'/2**(i+1), W'/2**(i+1))
        for encoder i, H' x W' the padded input; a zero previous reconstruction (N, 1, H', W')
        float32), in the layout of the network's outputs (channels-last when its weights are),
        so ``forward(voxel, initial_states(voxel))`` is bit-identical to
        ``forward(voxel, None)`` and a compiled network sees one input structure for every call
        of a sequence. The LSTM zeros take autocast's dtype when autocast is on for the voxel's
        device (the convolutions' outputs they stand beside), else the voxel's dtype: call it
        in the autocast region of the forward. With ``requires_grad`` the LSTM zeros are leaves
        that require grad, as the states the network returns in training do (a compiled graph
        guards on it); the parameters' gradients are the same either way
        (``trainer.models.layers.zero_lstm_states``). Raises ``ValueError`` for a voxel of the
        wrong shape."""
        check_voxel(voxel, self.num_bins)
        x, _, _ = pad_input(voxel)
        lstm = zero_lstm_states(self.unetrecurrent.encoders, x, requires_grad)
        fmt = output_memory_format(self.unetrecurrent.encoders[0].recurrent_block.Gates)
        return lstm, torch.empty((x.shape[0], 1) + x.shape[2:], dtype=x.dtype, device=x.device,
                                 memory_format=fmt).zero_()

    def forward(self, voxel: torch.Tensor, states: Optional[Tuple[List, torch.Tensor]] = None,
                gt_image: Optional[torch.Tensor] = None, beta: Union[float, torch.Tensor] = 0.0):
        check_voxel(voxel, self.num_bins)
        x, h, w = pad_input(voxel)
        u = self.unetrecurrent
        if states is None:
            lstm = [None] * self.num_encoders
            prev = x.new_zeros(x.shape[0], 1, x.shape[2], x.shape[3])
        else:
            lstm, prev = states
        if gt_image is not None and isinstance(beta, torch.Tensor):
            # beta a device tensor (``speed: fast``): one graph for every value of the curriculum
            # (a Python float is a constant of a compiled graph, so each value would be a new
            # graph). At the ends the result is bit-identical to the float path's: beta 0 keeps
            # the reconstruction (the float path skips the blend), beta 1 gives the frame
            # (the float path's prev * 0 + gt * 1)
            gt, _, _ = pad_input(gt_image)
            mixed = prev * (1 - beta) + gt * beta
            prev = torch.where(beta == 0, prev, torch.where(beta == 1, gt, mixed))
        elif gt_image is not None and beta > 0:
            gt, _, _ = pad_input(gt_image)
            prev = prev * (1 - beta) + gt * beta
        f = u.head(x)
        head = f
        blocks, new_lstm = [], []
        for enc, st in zip(u.encoders, lstm):
            f, st = enc(f, st)
            blocks.append(f)
            new_lstm.append(st)
        for res in u.resblocks:
            f = res(f)
        for i, dec in enumerate(u.decoders):
            f = f + blocks[self.num_encoders - i - 1]
            f = dec(f, x, prev) if i == 0 else dec(f)
        img = u.pred(f + head)
        return img[..., :h, :w], (new_lstm, img.detach())
