"""Optical flow between ground-truth frames from torchvision's RAFT at train time.

The V2V authors' training code (HYLZ-2019/V2V ``model/train_utils.py`` ``load_raft`` and
``inference_raft``; ``model/train_flow_utils.py``) computes the flow that temporal consistency
(reconstruction tasks, ``raft_small``) and EV-FlowNet's targets (``raft_large``) need from the
batch's ground-truth frames on the training device, 12 refinement iterations, instead of
reading it from the dataset. ``loss.flow_source: raft-small | raft-large`` (the server's
``flow_preset`` names; ``raft_small`` / ``raft_large`` are read as them) does the same here;
the default ``stream`` uses the flow the server sends.

RAFT needs torchvision and local weights (nothing is downloaded): ``loss.raft_weights``, else
``$V2V_RAFT_WEIGHTS``, else torchvision's cache ``$TORCH_HOME/hub/checkpoints/raft_<size>*.pth``
(``v2v_server.flow.options.load_raft``, the server's RAFT loader, looks in the same
places and loads the network). :func:`load_raft` checks both before the first step and raises
:class:`FlowSourceUnavailable` naming what is missing.

The pre- and post-processing (:func:`raft_pair_flow`) takes the network as an argument, so it
is tested with a stand-in network where torchvision is not installed.
"""
from __future__ import annotations

from typing import Callable, Optional

import torch

from v2v_server.flow.options import FlowUnavailable, load_raft as load_raft_network

from .config import FLOW_SOURCES, SPELLINGS

__all__ = ["FLOW_SOURCES", "FlowSourceUnavailable", "load_raft", "raft_pair_flow", "RaftFlow"]

#: RAFT's input sides are padded to a multiple of this and to at least ``MIN_SIDE`` (the
#: authors' ``inference_raft``: RAFT's feature pyramid needs both).
PAD_MULTIPLE, MIN_SIDE = 8, 128


class FlowSourceUnavailable(FlowUnavailable):
    """``loss.flow_source`` names RAFT but torchvision or the weight file is missing."""


def load_raft(source: str, device: torch.device, weights: Optional[str] = None) -> torch.nn.Module:
    """torchvision's RAFT small or large (``source``: ``raft-small`` or ``raft-large``, or
    ``raft_small`` / ``raft_large``) with local weights (``weights``: ``loss.raft_weights``, None:
    the server's places), in eval mode on ``device``, its parameters frozen; loaded by the
    server's loader (``v2v_server.flow.options.load_raft``).

    Raises:
        ValueError: ``source`` names no RAFT.
        FlowSourceUnavailable: naming ``loss.flow_source``, when torchvision cannot be imported,
            no weight file is found (the message lists the places looked at), or the file does
            not load into the network.
    """
    source = SPELLINGS.get(source, source)
    if source not in FLOW_SOURCES[1:]:
        raise ValueError(f"loss.flow_source must be one of {list(FLOW_SOURCES[1:])} to load RAFT, got {source!r}")
    try:
        net = load_raft_network(source.split("-", 1)[1], weights)
    except FlowUnavailable as e:
        raise FlowSourceUnavailable(f"loss.flow_source={source}: {e}; or train with loss.flow_source=stream (the "
                                    f"server's flow)") from e
    return net.to(device)


def raft_pair_flow(net: Callable, a: torch.Tensor, b: torch.Tensor, num_flow_updates: int = 12) -> torch.Tensor:
    """Flow from frames ``a`` to ``b`` with a RAFT network, as the authors' ``inference_raft``.

    Args:
        net: ``net(img1, img2, num_flow_updates=k)`` returning a list of flow predictions
            (N, 2, H', W'), the last the finest (torchvision's RAFT).
        a, b: (N, 1, H, W) or (N, 3, H, W) float frames in [0, 1] (grey is repeated to 3
            channels), on the network's device.
        num_flow_updates: RAFT's refinement iterations (the authors: 12).

    Returns:
        float32 (N, 2, H, W), detached: channel 0 the x and channel 1 the y displacement in
        pixels of each pixel of ``a`` in ``b``. The inputs are scaled to [-1, 1] and
        zero-padded at the bottom and right to sides that are multiples of 8 and at least 128;
        the padding is cut from the result.

    Raises:
        ValueError: frames of different shapes or not (N, 1|3, H, W).
    """
    if a.shape != b.shape or a.ndim != 4 or a.shape[1] not in (1, 3):
        raise ValueError(f"RAFT frames must both be (N, 1|3, H, W), got {tuple(a.shape)} and {tuple(b.shape)}")
    n, c, h, w = a.shape
    ph = max(-(-h // PAD_MULTIPLE) * PAD_MULTIPLE, MIN_SIDE)
    pw = max(-(-w // PAD_MULTIPLE) * PAD_MULTIPLE, MIN_SIDE)

    def prep(x):
        out = torch.zeros((n, 3, ph, pw), dtype=torch.float32, device=x.device)
        out[:, :, :h, :w] = x.float() * 2 - 1  # grey broadcasts to the 3 channels
        return out

    with torch.no_grad():
        flow = net(prep(a), prep(b), num_flow_updates=int(num_flow_updates))[-1]
    return flow[:, :, :h, :w].float().detach()


class RaftFlow:
    """Flow of consecutive frames of a batch, for a task's loss (``loss.flow_source``).

    Args:
        source: ``raft-small`` or ``raft-large`` (or ``raft_small`` / ``raft_large``).
        device: the training device (RAFT runs there, under ``torch.no_grad``).
        num_flow_updates: RAFT's iterations (``loss.raft_num_flow_updates``).
        weights: ``loss.raft_weights`` (None: the server's places, ``flow.options.raft_weight_places``).
        net: a ready network instead of loading one (tests).

    Raises:
        FlowSourceUnavailable, ValueError: as :func:`load_raft`.
    """

    def __init__(self, source: str, device: torch.device, num_flow_updates: int = 12,
                 weights: Optional[str] = None, net: Optional[Callable] = None):
        self.source, self.num_flow_updates = source, int(num_flow_updates)
        self.net = net if net is not None else load_raft(source, device, weights)

    def __call__(self, frames: torch.Tensor, start: int = 0) -> torch.Tensor:
        """float32 (B, L - start, 2, H, W): entry k is the flow from ``frames[:, start + k]``
        to ``frames[:, start + k + 1]`` of ``frames`` (B, L + 1, 1, H, W) in [0, 1], the layout of
        the stream's ``flow[:, start:]``."""
        B, T = frames.shape[:2]
        a = frames[:, start:T - 1].flatten(0, 1)
        b = frames[:, start + 1:].flatten(0, 1)
        flow = raft_pair_flow(self.net, a, b, self.num_flow_updates)
        return flow.view(B, T - 1 - start, *flow.shape[1:])
