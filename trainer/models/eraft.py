"""E-RAFT: dense optical flow from two consecutive event voxel grids (Gehrig et al., "E-RAFT:
Dense Optical Flow from Event Cameras", 3DV 2021), as the V2V authors train it on V2V data
(HYLZ-2019/V2V ``model/eraft/``, ``config/train_v2v_eraft_10k.yaml``).

The network is RAFT (Teed & Deng, ECCV 2020) with voxel grids in place of images:

* a feature encoder ``fnet`` (instance norm) and a context encoder ``cnet`` (batch norm),
  both a 7x7 stride-2 convolution to 64 channels and three stages of two residual blocks
  (64, 96 stride 2, 128 stride 2) then a 1x1 convolution, so features are at 1/8 resolution:
  ``fnet`` 256 channels, ``cnet`` 128 hidden state (tanh) + 128 context (ReLU) channels;
* the all-pairs correlation volume of the two feature maps (dot product / sqrt(256)),
  average-pooled into a 4-level pyramid, looked up in a radius-4 window around the current
  flow at each level (4 x 81 = 324 channels);
* an update block (motion encoder, separable ConvGRU 1x5 then 5x1, flow head giving a flow
  increment at 1/8 resolution, and a 9-neighbour convex upsampling mask) run for ``iters``
  iterations (12).

Input pairing (the authors' ``forward_sequence_eraft``): voxel grid l-1 and voxel grid l give
the flow over voxel l's interval, frame l -> l+1 (the stream's ``flow[:, l]``). Warm start
(the authors' ``subtype: warm_start``, E-RAFT's sequential mode): the 1/8-resolution flow of
one call, forward-splatted along itself (:func:`forward_interpolate`), initialises the next
call; :meth:`ERAFT.reset_states` drops it at the start of each sequence.

Inputs are zero-padded at the top and left to multiples of 32 and the output cropped back
(the authors' ``ImagePadder(min_size=32)``). Their correlation lookup samples each pyramid
level with ``grid_sample(align_corners=True)`` after dividing by ``side - 1``, so every level
needs a side of at least 2: with the 4 levels, padded sides of at least 128 pixels (their
code gives NaN flow on 64 x 64). ``corr_levels=3`` (RAFT's ``args.corr_levels``) allows 64
pixels, for small CPU runs only: it changes the motion encoder's input width.

State-dict keys and shapes are the authors' (``fnet.*``, ``cnet.*``, ``update_block.*``),
so their ``v2v_eraft_10k`` checkpoint loads with ``load_state_dict``; 5,270,080 parameters
with 5 input bins (checked in ``tests/test_trainer_eraft.py`` against a listing derived from
their classes by ``harness/eraft_reference.py``).
"""
from __future__ import annotations

import math
from typing import List, Optional, Tuple

import torch
import torch.nn as nn
import torch.nn.functional as F

__all__ = ["ERAFT", "BasicEncoder", "UpdateBlock", "correlation_pyramid", "lookup_correlation",
           "forward_interpolate", "min_side", "PAD_MULTIPLE"]

#: Inputs are padded (top/left) to a multiple of this (the authors' ``ImagePadder(min_size=32)``).
PAD_MULTIPLE = 32
#: Correlation pyramid levels and lookup radius (E-RAFT / RAFT defaults).
CORR_LEVELS, CORR_RADIUS = 4, 4


def _pads(H: int, W: int) -> Tuple[int, int]:
    """Rows and columns of padding that bring H x W to multiples of :data:`PAD_MULTIPLE`."""
    return (-H) % PAD_MULTIPLE, (-W) % PAD_MULTIPLE


def min_side(corr_levels: int = CORR_LEVELS) -> int:
    """Smallest padded input side whose coarsest correlation level has two cells: features at
    1/8, halved ``corr_levels - 1`` times (128 for 4 levels, 64 for 3)."""
    return 16 * 2 ** (corr_levels - 1)


def _norm(kind: str, channels: int) -> nn.Module:
    """Normalisation layer of the encoders: ``instance`` (no affine, as RAFT's fnet), ``batch``,
    ``group`` (channels / 8 groups) or ``none``."""
    if kind == "instance":
        return nn.InstanceNorm2d(channels)
    if kind == "batch":
        return nn.BatchNorm2d(channels)
    if kind == "group":
        return nn.GroupNorm(channels // 8, channels)
    if kind == "none":
        return nn.Sequential()
    raise ValueError(f"norm must be instance, batch, group or none, got {kind!r}")


class ResidualBlock(nn.Module):
    """Two 3x3 convolutions with norm + ReLU and a residual connection; with stride 2 the
    shortcut is a strided 1x1 convolution followed by ``norm3`` (held twice, as ``norm3`` and
    ``downsample.1``, the authors' layout: both names are in the state dict)."""

    def __init__(self, cin: int, cout: int, norm: str, stride: int = 1):
        super().__init__()
        self.conv1 = nn.Conv2d(cin, cout, 3, padding=1, stride=stride)
        self.conv2 = nn.Conv2d(cout, cout, 3, padding=1)
        self.relu = nn.ReLU(inplace=True)
        self.norm1, self.norm2 = _norm(norm, cout), _norm(norm, cout)
        self.downsample = None
        if stride != 1:
            self.norm3 = _norm(norm, cout)
            self.downsample = nn.Sequential(nn.Conv2d(cin, cout, 1, stride=stride), self.norm3)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.relu(self.norm1(self.conv1(x)))
        y = self.relu(self.norm2(self.conv2(y)))
        if self.downsample is not None:
            x = self.downsample(x)
        return self.relu(x + y)


class BasicEncoder(nn.Module):
    """RAFT's feature / context encoder: (N, in_channels, H, W) -> (N, output_dim, H/8, W/8).

    Convolutions are initialised Kaiming-normal (fan out, ReLU), norm weights 1 and biases 0,
    as RAFT's. ``forward`` takes one tensor, or a pair that is run as one batch and split
    again (the feature encoder's two voxel grids share instance-norm statistics per sample
    only, so batching them changes nothing but speed)."""

    def __init__(self, output_dim: int = 128, norm: str = "batch", in_channels: int = 1):
        super().__init__()
        self.norm1 = _norm(norm, 64)
        self.conv1 = nn.Conv2d(in_channels, 64, 7, stride=2, padding=3)
        self.relu1 = nn.ReLU(inplace=True)
        self.layer1 = nn.Sequential(ResidualBlock(64, 64, norm, 1), ResidualBlock(64, 64, norm, 1))
        self.layer2 = nn.Sequential(ResidualBlock(64, 96, norm, 2), ResidualBlock(96, 96, norm, 1))
        self.layer3 = nn.Sequential(ResidualBlock(96, 128, norm, 2), ResidualBlock(128, 128, norm, 1))
        self.conv2 = nn.Conv2d(128, output_dim, 1)
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
            elif isinstance(m, (nn.BatchNorm2d, nn.InstanceNorm2d, nn.GroupNorm)):
                if m.weight is not None:
                    nn.init.constant_(m.weight, 1)
                if m.bias is not None:
                    nn.init.constant_(m.bias, 0)

    def forward(self, x):
        pair = isinstance(x, (list, tuple))
        if pair:
            n = x[0].shape[0]
            x = torch.cat(list(x), dim=0)
        x = self.relu1(self.norm1(self.conv1(x)))
        x = self.conv2(self.layer3(self.layer2(self.layer1(x))))
        return torch.split(x, [n, n], dim=0) if pair else x


class MotionEncoder(nn.Module):
    """Correlation features (324 channels) and the current flow (2) -> 126 motion channels + the
    flow itself (128 in all), RAFT's ``BasicMotionEncoder``."""

    def __init__(self, corr_planes: int):
        super().__init__()
        self.convc1 = nn.Conv2d(corr_planes, 256, 1)
        self.convc2 = nn.Conv2d(256, 192, 3, padding=1)
        self.convf1 = nn.Conv2d(2, 128, 7, padding=3)
        self.convf2 = nn.Conv2d(128, 64, 3, padding=1)
        self.conv = nn.Conv2d(64 + 192, 128 - 2, 3, padding=1)

    def forward(self, flow: torch.Tensor, corr: torch.Tensor) -> torch.Tensor:
        c = F.relu(self.convc2(F.relu(self.convc1(corr))))
        f = F.relu(self.convf2(F.relu(self.convf1(flow))))
        return torch.cat([F.relu(self.conv(torch.cat([c, f], dim=1))), flow], dim=1)


class SepConvGRU(nn.Module):
    """Convolutional GRU applied twice, with 1x5 then 5x1 kernels (RAFT's ``SepConvGRU``):
    h' = (1 - z) h + z q, z = sigmoid(conv_z[h, x]), r = sigmoid(conv_r[h, x]),
    q = tanh(conv_q[r h, x])."""

    def __init__(self, hidden_dim: int = 128, input_dim: int = 256):
        super().__init__()
        c = hidden_dim + input_dim
        for axis, (k, p) in (("1", ((1, 5), (0, 2))), ("2", ((5, 1), (2, 0)))):
            for gate in "zrq":
                setattr(self, f"conv{gate}{axis}", nn.Conv2d(c, hidden_dim, k, padding=p))

    def _half(self, h: torch.Tensor, x: torch.Tensor, axis: str) -> torch.Tensor:
        hx = torch.cat([h, x], dim=1)
        z = torch.sigmoid(getattr(self, f"convz{axis}")(hx))
        r = torch.sigmoid(getattr(self, f"convr{axis}")(hx))
        q = torch.tanh(getattr(self, f"convq{axis}")(torch.cat([r * h, x], dim=1)))
        return (1 - z) * h + z * q

    def forward(self, h: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        return self._half(self._half(h, x, "1"), x, "2")


class FlowHead(nn.Module):
    """Two 3x3 convolutions (ReLU between): hidden state -> flow increment (N, 2, h, w)."""

    def __init__(self, input_dim: int = 128, hidden_dim: int = 256):
        super().__init__()
        self.conv1 = nn.Conv2d(input_dim, hidden_dim, 3, padding=1)
        self.conv2 = nn.Conv2d(hidden_dim, 2, 3, padding=1)
        self.relu = nn.ReLU(inplace=True)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.conv2(self.relu(self.conv1(x)))


class UpdateBlock(nn.Module):
    """One RAFT iteration (``BasicUpdateBlock``): motion features, GRU step, flow increment and
    the upsampling mask (N, 64 * 9, h, w), scaled by 0.25 as RAFT's (to balance gradients)."""

    def __init__(self, corr_planes: int, hidden_dim: int = 128):
        super().__init__()
        self.encoder = MotionEncoder(corr_planes)
        self.gru = SepConvGRU(hidden_dim, 128 + hidden_dim)
        self.flow_head = FlowHead(hidden_dim, 256)
        self.mask = nn.Sequential(nn.Conv2d(128, 256, 3, padding=1), nn.ReLU(inplace=True),
                                  nn.Conv2d(256, 64 * 9, 1))

    def forward(self, net, inp, corr, flow):
        x = torch.cat([inp, self.encoder(flow, corr)], dim=1)
        net = self.gru(net, x)
        return net, 0.25 * self.mask(net), self.flow_head(net)


def pixel_grid(n: int, h: int, w: int, device=None) -> torch.Tensor:
    """float32 (n, 2, h, w) pixel coordinates: channel 0 = x (column), 1 = y (row)."""
    ys, xs = torch.meshgrid(torch.arange(h, device=device, dtype=torch.float32),
                            torch.arange(w, device=device, dtype=torch.float32), indexing="ij")
    return torch.stack([xs, ys])[None].expand(n, 2, h, w).contiguous()


def correlation_pyramid(f1: torch.Tensor, f2: torch.Tensor, levels: int = CORR_LEVELS) -> List[torch.Tensor]:
    """All-pairs correlation of feature maps (N, D, h, w): level 0 is (N h w, 1, h, w), entry
    [i, 0] the dot products of pixel i of ``f1`` with every pixel of ``f2`` divided by
    sqrt(D); each further level average-pools the previous by 2 (RAFT's ``CorrBlock``)."""
    n, d, h, w = f1.shape
    corr = torch.matmul(f1.reshape(n, d, h * w).transpose(1, 2), f2.reshape(n, d, h * w))
    corr = corr.reshape(n * h * w, 1, h, w) / math.sqrt(d)
    out = [corr]
    for _ in range(levels - 1):
        corr = F.avg_pool2d(corr, 2, stride=2)
        out.append(corr)
    return out


def lookup_correlation(pyramid: List[torch.Tensor], coords: torch.Tensor, radius: int = CORR_RADIUS) -> torch.Tensor:
    """Correlation values around ``coords`` (N, 2, h, w) (x, y in level-0 pixels): at each level
    i a (2r+1)^2 window centred on coords / 2^i, bilinearly sampled (zeros outside, corners
    aligned as RAFT's ``bilinear_sampler``). Returns float32 (N, levels (2r+1)^2, h, w), window
    offsets ordered x-major within each level as RAFT's."""
    n, _, h, w = coords.shape
    c = coords.permute(0, 2, 3, 1).reshape(n * h * w, 1, 1, 2)
    d = torch.arange(-radius, radius + 1, device=coords.device, dtype=coords.dtype)
    # RAFT builds the window as stack(meshgrid(dy, dx)) and adds it to (x, y): the first
    # component (added to x) varies along the window's rows.
    off = torch.stack(torch.meshgrid(d, d, indexing="ij"), dim=-1).view(1, 2 * radius + 1, 2 * radius + 1, 2)
    out = []
    for i, corr in enumerate(pyramid):
        xy = c / 2 ** i + off
        hh, ww = corr.shape[-2:]
        grid = torch.cat([2 * xy[..., :1] / (ww - 1) - 1, 2 * xy[..., 1:] / (hh - 1) - 1], dim=-1)
        out.append(F.grid_sample(corr, grid, align_corners=True).view(n, h, w, -1))
    return torch.cat(out, dim=-1).permute(0, 3, 1, 2).contiguous().float()


def forward_interpolate(flow: torch.Tensor) -> torch.Tensor:
    """Forward-splat a flow (N, 2, h, w) along itself: each pixel's flow is moved to where it
    points and spread bilinearly over the four neighbours (floor/ceil of x and y) with weights
    (1 - |dx|)(1 - |dy|); each target pixel gets the weighted mean of what lands on it, 0 where
    nothing does. The E-RAFT authors' ``forward_interpolate_pytorch`` (their warm start), with
    its quirk kept: on an integer coordinate floor = ceil, so that corner is counted twice
    (the mean is unchanged). Returns a new float32 tensor of the same shape."""
    n, _, h, w = flow.shape
    flow = flow.float()
    base = pixel_grid(n, h, w, flow.device).flatten(2)  # (n, 2, h w)
    f = flow.flatten(2)
    tx, ty = base[:, 0] + f[:, 0], base[:, 1] + f[:, 1]
    vals = torch.zeros(n, 2, h * w, device=flow.device)
    wsum = torch.zeros(n, h * w, device=flow.device)
    for xv in (torch.floor(tx), torch.ceil(tx)):
        for yv in (torch.floor(ty), torch.ceil(ty)):
            inside = (xv < w) & (xv >= 0) & (yv < h) & (yv >= 0)
            wt = (1 - (tx - xv).abs()) * (1 - (ty - yv).abs()) * inside
            idx = torch.where(inside, xv + w * yv, torch.zeros_like(xv)).long()
            wsum.scatter_add_(1, idx, wt)
            vals.scatter_add_(2, idx[:, None].expand(n, 2, h * w), f * wt[:, None])
    return (vals / (wsum[:, None] + 1e-15)).view(n, 2, h, w)


class ERAFT(nn.Module):
    """E-RAFT with the V2V authors' settings (``config/train_v2v_eraft_10k.yaml``): 5 input bins
    ("n_first_channels: 5"), warm start, 12 iterations.

    Args:
        num_bins: bins per voxel grid (the authors' ``n_first_channels``; the original E-RAFT
            DSEC model: 15).
        subtype: ``warm_start`` (the flow of the previous call initialises the next) or
            ``standard`` (every call starts from zero flow, the E-RAFT paper's non-sequential
            mode; the authors' V2V wrapper carries the flow in both).
        iters: refinement iterations per call (the authors' 12).
        corr_levels, corr_radius: correlation pyramid levels and lookup radius (4 and 4, the
            authors'; other values change the motion encoder's input width, so their
            checkpoints no longer load).

    ``forward(voxel_prev, voxel)``: float (N, num_bins, H, W) each, the grids of two consecutive
    intervals -> float32 (N, 2, H, W), the flow over ``voxel``'s interval in pixels (channel 0
    = x, 1 = y), from the last iteration. Stateful: with warm start the 1/8-resolution flow is
    kept for the next call until :meth:`reset_states`. Raises ``ValueError`` for inputs of the
    wrong shape, and for padded sides under :func:`min_side`.
    """

    def __init__(self, num_bins: int, subtype: str, iters: int, corr_levels: int, corr_radius: int):
        super().__init__()
        subtype = str(subtype).lower()
        if subtype not in ("warm_start", "standard"):
            raise ValueError(f"subtype must be 'warm_start' or 'standard', got {subtype!r}")
        self.num_bins, self.subtype, self.iters = int(num_bins), subtype, int(iters)
        self.corr_levels, self.corr_radius = int(corr_levels), int(corr_radius)
        self.hidden_dim = self.context_dim = 128
        self.fnet = BasicEncoder(256, "instance", self.num_bins)
        self.cnet = BasicEncoder(self.hidden_dim + self.context_dim, "batch", self.num_bins)
        self.update_block = UpdateBlock(self.corr_levels * (2 * self.corr_radius + 1) ** 2, self.hidden_dim)
        self.flow_init: Optional[torch.Tensor] = None

    def reset_states(self, voxel: Optional[torch.Tensor] = None) -> None:
        """Forget the warm-start flow (call at the start of every sequence). With ``voxel``
        (N, num_bins, H, W), a grid of the coming sequence, and warm start on, the flow becomes
        zeros of its shape (N, 2, H'/8, W'/8) float32, H' x W' the padded sides, instead of
        None: the first call's coordinates plus 0 are the coordinates (bit-identical), and a
        compiled network sees a tensor on every call, so one graph serves the whole sequence."""
        self.flow_init = None
        if voxel is not None and self.subtype == "warm_start":
            H, W = voxel.shape[-2:]
            ph, pw = _pads(H, W)
            self.flow_init = torch.zeros(voxel.shape[0], 2, (H + ph) // 8, (W + pw) // 8, device=voxel.device)

    @staticmethod
    def _upsample(flow: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """(N, 2, h, w) flow at 1/8 -> (N, 2, 8h, 8w): each fine pixel a softmax-weighted convex
        combination of the 3x3 coarse neighbours of 8 x flow (RAFT's ``upsample_flow``)."""
        n, _, h, w = flow.shape
        mask = torch.softmax(mask.reshape(n, 1, 9, 8, 8, h, w), dim=2)
        up = F.unfold(8 * flow, [3, 3], padding=1).view(n, 2, 9, 1, 1, h, w)
        up = torch.sum(mask * up, dim=2).permute(0, 1, 4, 2, 5, 3)
        return up.reshape(n, 2, 8 * h, 8 * w)

    def forward(self, voxel_prev: torch.Tensor, voxel: torch.Tensor, iters: Optional[int] = None) -> torch.Tensor:
        for name, v in (("voxel_prev", voxel_prev), ("voxel", voxel)):
            if v.ndim != 4 or v.shape[1] != self.num_bins:
                raise ValueError(f"{name} must be (N, {self.num_bins}, H, W), got {tuple(v.shape)}")
        if voxel_prev.shape != voxel.shape:
            raise ValueError(f"voxel grids differ in shape: {tuple(voxel_prev.shape)} vs {tuple(voxel.shape)}")
        low, flows = self.forward_all(voxel_prev, voxel, iters)
        if self.subtype == "warm_start":
            self.flow_init = forward_interpolate(low.detach())
        return flows[-1]

    def forward_all(self, voxel_prev: torch.Tensor, voxel: torch.Tensor,
                    iters: Optional[int] = None) -> Tuple[torch.Tensor, List[torch.Tensor]]:
        """The 1/8-resolution flow of the padded input after the last iteration (N, 2, H'/8,
        W'/8) and the upsampled, cropped flow of every iteration (``iters`` x (N, 2, H, W));
        uses but does not update the warm-start flow."""
        H, W = voxel.shape[-2:]
        ph, pw = _pads(H, W)
        side = min_side(self.corr_levels)
        if H + ph < side or W + pw < side:
            raise ValueError(f"E-RAFT with {self.corr_levels} correlation levels needs padded sides >= {side} (its "
                             f"coarsest level must have two cells); got {H}x{W}, padded {H + ph}x{W + pw}")
        a = F.pad(voxel_prev, (pw, 0, ph, 0)).contiguous()
        b = F.pad(voxel, (pw, 0, ph, 0)).contiguous()
        f1, f2 = self.fnet([a, b])
        with torch.autocast(device_type=a.device.type, enabled=False):
            pyramid = correlation_pyramid(f1.float(), f2.float(), self.corr_levels)
        net, inp = torch.split(self.cnet(b), [self.hidden_dim, self.context_dim], dim=1)
        net, inp = torch.tanh(net), torch.relu(inp)
        n, _, h8, w8 = f1.shape
        coords0 = pixel_grid(n, h8, w8, a.device)
        coords1 = coords0.clone()
        if self.flow_init is not None:
            if self.flow_init.shape != coords1.shape:
                raise ValueError(f"warm-start flow {tuple(self.flow_init.shape)} does not fit input "
                                 f"{tuple(voxel.shape)}; call reset_states() between sequences")
            coords1 = coords1 + self.flow_init
        flows = []
        for _ in range(self.iters if iters is None else int(iters)):
            coords1 = coords1.detach()
            corr = lookup_correlation(pyramid, coords1, self.corr_radius)
            net, mask, delta = self.update_block(net, inp, corr, coords1 - coords0)
            coords1 = coords1 + delta.float()
            flows.append(self._upsample(coords1 - coords0, mask.float())[..., ph:, pw:])
        return coords1 - coords0, flows
