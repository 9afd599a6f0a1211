"""LPIPS (Zhang et al., CVPR 2018, "The Unreasonable Effectiveness of Deep Features as a
Perceptual Metric"), v0.1 "lin" variant, re-implemented in plain torch.

The ``lpips`` pip package needs torchvision, which has no CPU build here, so the two
backbones are written out (VGG16 and AlexNet feature stacks, layer for layer as in
torchvision, so their state dicts load unchanged) together with the five 1x1 linear heads.

No weights are bundled and none are downloaded. :func:`load_lpips` loads them from local
files (config keys ``lpips_weights``), or uses an installed ``lpips`` package if one is
importable and can build its model offline, and otherwise returns ``None`` so the caller
falls back to an SSIM term (logged once).

Accepted weight files (any mix, merged in order; ``module.`` prefixes are stripped):

* a full ``lpips.LPIPS(net=...).state_dict()`` saved with ``torch.save`` (keys
  ``net.sliceK.N.*`` and ``linK.model.1.weight``);
* the package's linear-head file ``lpips/weights/v0.1/{vgg,alex}.pth`` (``linK.model.1.weight``)
  plus torchvision's ImageNet backbone (``vgg16-397923af.pth`` / ``alexnet-owt-7be5be79.pth``,
  keys ``features.N.*``);
* this module's own ``state_dict()`` (``features.N.*``, ``lins.K.weight``).
"""
from __future__ import annotations

import logging
import os
import re
from typing import List, Optional, Sequence, Union

import torch
import torch.nn as nn

__all__ = ["LPIPSNet", "load_lpips", "convert_state_dict", "STAND_IN", "LPIPSUnavailable"]

log = logging.getLogger(__name__)

#: What a result records as its perceptual term when no LPIPS weights were found and 1 - SSIM
#: (win 7, data_range 1) stood in for LPIPS: ``summary.json``, checkpoints' metadata,
#: ``v2v-eval``'s JSON and tables. Such a result is not comparable with the paper's.
STAND_IN = "1-ssim (stand-in: no LPIPS weights)"


class LPIPSUnavailable(RuntimeError):
    """``--require-lpips`` was given and no LPIPS weights were found (``v2v-train`` and
    ``v2v-eval`` exit with status 2)."""

# (torchvision features layout, indices after which a feature map is tapped, channels)
_VGG16_CFG = [64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512, "M"]
_TAPS = {"vgg": (3, 8, 15, 22, 29), "alex": (1, 4, 7, 9, 11)}
_CHANNELS = {"vgg": (64, 128, 256, 512, 512), "alex": (64, 192, 384, 256, 256)}
# LPIPS ScalingLayer constants (inputs in [-1, 1]).
_SHIFT = (-0.030, -0.088, -0.188)
_SCALE = (0.458, 0.448, 0.450)


def _vgg16_features() -> nn.Sequential:
    layers: List[nn.Module] = []
    cin = 3
    for v in _VGG16_CFG:
        if v == "M":
            layers.append(nn.MaxPool2d(2, 2))
        else:
            layers += [nn.Conv2d(cin, v, 3, padding=1), nn.ReLU(inplace=False)]
            cin = v
    return nn.Sequential(*layers)


def _alexnet_features() -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(3, 64, 11, stride=4, padding=2), nn.ReLU(inplace=False), nn.MaxPool2d(3, 2),
        nn.Conv2d(64, 192, 5, padding=2), nn.ReLU(inplace=False), nn.MaxPool2d(3, 2),
        nn.Conv2d(192, 384, 3, padding=1), nn.ReLU(inplace=False),
        nn.Conv2d(384, 256, 3, padding=1), nn.ReLU(inplace=False),
        nn.Conv2d(256, 256, 3, padding=1), nn.ReLU(inplace=False), nn.MaxPool2d(3, 2),
    )


class LPIPSNet(nn.Module):
    """LPIPS v0.1 distance with a VGG16 or AlexNet backbone (frozen, eval mode).

    Args:
        net: ``'vgg'`` (the E2VID training loss) or ``'alex'`` (the evaluation metric).

    ``forward(x, y)``: x, y float (N, C, H, W) with C = 1 (grey, repeated to RGB) or 3,
    intensities in [0, 1] (mapped to [-1, 1] as ``lpips(..., normalize=True)`` does).
    Returns the distance per image, float (N,). Raises ``ValueError`` for other shapes.
    Freshly constructed weights are random: load real ones with :func:`load_lpips`.
    """

    def __init__(self, net: str = "vgg"):
        super().__init__()
        if net not in _TAPS:
            raise ValueError(f"net must be 'vgg' or 'alex', got {net!r}")
        self.net_type = net
        self.features = _vgg16_features() if net == "vgg" else _alexnet_features()
        self.taps = _TAPS[net]
        self.lins = nn.ModuleList([nn.Conv2d(c, 1, 1, bias=False) for c in _CHANNELS[net]])
        self.register_buffer("shift", torch.tensor(_SHIFT).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("scale", torch.tensor(_SCALE).view(1, 3, 1, 1), persistent=False)
        self.requires_grad_(False)
        self.eval()

    def train(self, mode: bool = True):  # always eval: no dropout, frozen backbone
        return super().train(False)

    def _taps(self, x: torch.Tensor) -> List[torch.Tensor]:
        out = []
        last = self.taps[-1]
        for i, layer in enumerate(self.features):
            x = layer(x)
            if i in self.taps:
                out.append(x)
            if i == last:
                break
        return out

    def forward(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        if x.shape != y.shape or x.ndim != 4 or x.shape[1] not in (1, 3):
            raise ValueError(f"expected two equal (N, 1|3, H, W) tensors, got {tuple(x.shape)}, {tuple(y.shape)}")
        if x.shape[1] == 1:
            x, y = x.expand(-1, 3, -1, -1), y.expand(-1, 3, -1, -1)
        n = x.shape[0]
        z = torch.cat([x, y], 0).float() * 2.0 - 1.0
        z = (z - self.shift) / self.scale
        total = z.new_zeros(n)
        for k, f in enumerate(self._taps(z)):
            f = f / (torch.sqrt(torch.sum(f * f, dim=1, keepdim=True)) + 1e-10)
            d = (f[:n] - f[n:]) ** 2
            total = total + self.lins[k](d).mean(dim=(1, 2, 3))
        return total


def convert_state_dict(sd: dict) -> dict:
    """Map the key names of the accepted weight files (module docstring) onto
    :class:`LPIPSNet`'s (``features.N.*``, ``lins.K.weight``); unrelated keys (the
    package's ``scaling_layer.*``, torchvision's ``classifier.*``) are dropped."""
    out = {}
    for k, v in sd.items():
        k = re.sub(r"^module\.", "", k)
        m = re.fullmatch(r"net\.slice\d\.(\d+)\.(weight|bias)", k) or re.fullmatch(r"features\.(\d+)\.(weight|bias)", k)
        if m:
            out[f"features.{m.group(1)}.{m.group(2)}"] = v
            continue
        m = re.fullmatch(r"lin(\d)\.model\.1\.weight", k) or re.fullmatch(r"lins\.(\d)\.weight", k)
        if m:
            out[f"lins.{m.group(1)}.weight"] = v
    return out


class _PackageLPIPS(nn.Module):
    """Adapter around an installed ``lpips.LPIPS`` with :class:`LPIPSNet`'s interface."""

    def __init__(self, model: nn.Module, net: str):
        super().__init__()
        self.model = model.eval().requires_grad_(False)
        self.net_type = net

    def train(self, mode: bool = True):
        return super().train(False)

    def forward(self, x, y):
        if x.shape[1] == 1:
            x, y = x.expand(-1, 3, -1, -1), y.expand(-1, 3, -1, -1)
        return self.model(x.float(), y.float(), normalize=True).flatten()


def load_lpips(net: str = "vgg", weights: Union[None, str, Sequence[str]] = None,
               use_package: bool = True) -> Optional[nn.Module]:
    """Return a frozen LPIPS distance module with real weights, or ``None`` when there are none.

    Args:
        net: ``'vgg'`` or ``'alex'``.
        weights: local path or list of paths (module docstring lists the accepted files).
            When given, every backbone and head parameter must be covered.
        use_package: try ``import lpips`` when no path is given.

    Returns:
        A module mapping ``(x, y)`` (N, 1|3, H, W) in [0, 1] to distances (N,), or ``None``.

    Raises:
        FileNotFoundError: a given path does not exist.
        ValueError: the given files do not cover all parameters (missing keys are named).
    """
    if weights:
        paths = [weights] if isinstance(weights, (str, os.PathLike)) else list(weights)
        merged = {}
        for p in paths:
            p = os.path.expanduser(str(p))
            if not os.path.isfile(p):
                raise FileNotFoundError(f"LPIPS weight file not found: {p}")
            sd = torch.load(p, map_location="cpu", weights_only=True)
            if isinstance(sd, dict) and "state_dict" in sd and isinstance(sd["state_dict"], dict):
                sd = sd["state_dict"]
            merged.update(convert_state_dict(sd))
        model = LPIPSNet(net)
        expected = set(model.state_dict())
        missing = sorted(expected - set(merged))
        if missing:
            raise ValueError(f"LPIPS ({net}) weights incomplete, missing {len(missing)} keys, e.g. {missing[:4]}")
        model.load_state_dict({k: merged[k] for k in expected})
        return model
    if use_package:
        try:
            import lpips  # type: ignore

            return _PackageLPIPS(lpips.LPIPS(net=net, verbose=False), net)
        except Exception as e:  # not installed, or it would need to download weights
            log.debug("lpips package unusable: %s", e)
    return None
