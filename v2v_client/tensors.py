"""A batch's wire arrays as torch tensors (torch: ``pip install 'v2v[client]'``). The reader
(``plan_dataset``) imports this module, so it needs torch too; what a reader without torch has is
``v2v_wire`` (the messages, ``plan_messages``, and the arrays they carry, as numpy arrays:
``codecs.decode_batch_arrays``) and the client's endpoint handling (``endpoints``), which import
without it (``tests/test_client_install.py`` reads a server's rows so in a venv without torch)."""
from __future__ import annotations

import warnings
from typing import Dict, Optional, Tuple

import numpy as np
import torch

from v2v_wire.outputs import ARRAYS
from v2v_wire.protocol import ProtocolError

from .flowgrid import expand_flow_grid

__all__ = ["batch_to_torch"]


def _view(a: np.ndarray) -> torch.Tensor:
    """A tensor sharing ``a``'s memory (the received message's buffer, read-only)."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="The given NumPy array is not writable")
        return torch.from_numpy(a)


def batch_to_torch(arrays: Dict[str, np.ndarray], raw: bool = False, flow_size: Optional[Tuple[int, int]] = None,
                   flow_dtype: str = ARRAYS["flow"].dtypes[0]) -> Dict[str, torch.Tensor]:
    """Convert wire arrays of one batch to tensors, as their ``outputs.ArraySpec`` says.

    With ``raw=False``: ``voxels`` float32 (B, L, num_bins, H, W) event counts; ``frames``
    float32 in [0, 1] (B, L + 1, 1, H, W); ``flow`` float32 (B, L, 2, H, W), pixels;
    ``polarity_counts`` float32 (B, L, 2, num_bins, H, W) counts (one conversion pass per
    array on this host). With ``raw=True`` the wire dtypes are kept (voxels int8/int16/int32,
    frames uint8 with the channel axis, flow float16, polarity counts uint8) and nothing is
    copied: the tensors view the received message and must be treated as read-only
    (``.to(device)`` and ``.float()`` copy); convert on the GPU.

    A tracked flow option's flow arrives as ``flow_grid`` float32 (B, L, 2, n, n), its values
    at the tracking grid's points: it becomes ``flow`` (B, L, 2, *flow_size*) with the
    server's own bilinear taps (``flowgrid``): float32, or ``flow_dtype`` (the server's dense
    flow dtype) with ``raw``, equal to the dense flow the server would have sent.

    Raises:
        ProtocolError: an unknown array, a ``flow_grid`` of the wrong shape, or one with no
            ``flow_size`` to expand it to.
    """
    out = {}
    for name, a in arrays.items():
        spec = ARRAYS.get(name)
        if spec is None:
            raise ProtocolError(f"unknown array {name!r} in a batch; known: {list(ARRAYS)}")
        if spec.insert_channel:
            a = np.expand_dims(a, spec.channel_axis + 1)  # + 1: the batch axis
        if spec.expand:
            out.update(_expand(name, a, raw, flow_size, flow_dtype))
        elif raw:
            out[name] = _view(a)
        elif spec.float_divisor is not None:
            out[name] = torch.from_numpy(np.multiply(a, np.float32(1.0 / spec.float_divisor), dtype=np.float32))
        else:
            out[name] = torch.from_numpy(a.astype(np.float32))
    return out


def _expand(name: str, a: np.ndarray, raw: bool, flow_size, flow_dtype: str) -> Dict[str, torch.Tensor]:
    """A compact array (``flow_grid`` float32 (B, L, 2, n, n)) expanded to the dense output it
    carries (see :func:`batch_to_torch`)."""
    spec = ARRAYS[name]
    if a.ndim != 5 or a.shape[2] != 2 or a.shape[3] != a.shape[4] or a.shape[3] < 2 or a.dtype.name not in spec.dtypes:
        raise ProtocolError(f"array {name!r} must be {spec.dtypes[0]} (B, L, 2, n, n), got {a.dtype}{list(a.shape)}")
    if flow_size is None:
        raise ProtocolError(f"a {name!r} array, but the server's stream info named no crop_size to expand it to")
    dense = ARRAYS[spec.output].dtypes  # the dense output's wire dtypes: torch has the same names
    dtype = getattr(torch, flow_dtype) if raw and flow_dtype in dense else torch.float32
    return {spec.output: expand_flow_grid(_view(a), flow_size, dtype)}

