"""EV-FlowNet (UNet) in PyTorch, as the V2V paper's reference training configs build it (Lou et al.,
NeurIPS 2025; event_cnn_minimal, Stoffregen et al., ECCV 2020): the reference's ``UNet`` with no
head layer: 4 strided-conv encoders (5 -> 64 -> 128 -> 256 -> 512, k3) -> 2 residual blocks -> 4
upsample-conv decoders with *concat* skips (to 256, 128, 64, 32) -> 1x1 prediction conv 32 -> 2
(optical flow in pixels, channel 0 = x/u, 1 = y/v), parameters named as the reference's.
"""
from __future__ import annotations

import torch
import torch.nn as nn

from .layers import ConvLayer, ResidualBlock, UpsampleConvLayer, check_unet_args, check_voxel, pad_input

__all__ = ["UNet", "EVFlowNet"]


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
        check_unet_args(num_bins, base_num_channels, num_encoders, skip_type)
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
        check_voxel(voxel, self.num_bins)
        x, h, w = pad_input(voxel)
        return self.unet(x)[..., :h, :w]

