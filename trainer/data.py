"""Stream side of the trainer: which outputs each task asks ``v2v-serve`` for,
``v2v_client.V2VStreamDataset`` read epoch after epoch (:class:`PlanEpochs`) ahead of the loop
(:class:`ReadAhead`), and the host -> device transfer.

Batches (the client's contract): ``voxels`` (B, L, num_bins, H, W) int8/int16 when
``raw=True`` (float32 otherwise; signed event counts per bin), ``frames`` (B, L+1, 1, H, W)
uint8 (float32 in [0, 1] otherwise), frame l at voxel boundary l, ``flow`` (B, L, 2, H, W)
float16 (float32 otherwise), forward optical flow in pixels from frame l to l+1 (the dtypes and
float conversions of ``v2v_wire.outputs``). Integers and halves cross the PCIe bus; conversion to float32 happens on the device.
"""
from __future__ import annotations

from typing import Iterable, Optional, Sequence, Tuple

import torch
from torch.utils.data import DataLoader

from v2v_client.plan_dataset import PlanEpochs, PlanServerError, open_stream
from v2v_client.read_ahead import READ_AHEAD, ReadAhead
from v2v_wire.outputs import ARRAYS
from v2v_wire.plan import PlanMismatch

from .tasks import get_task

#: What reading a server raises when it is absent, silent or refuses (each message names the
#: server and why, in one line): v2v-train ends with that line.
STREAM_ERRORS = (TimeoutError, PlanServerError, PlanMismatch)

__all__ = ["make_stream", "STREAM_ERRORS", "PlanEpochs", "ReadAhead", "READ_AHEAD", "read_path", "close_read_path",
           "make_loader", "batch_to_device", "drop_padding"]


def make_stream(endpoint: str, task: str, timeout_s: float = 60.0, raw: bool = True, curve_keys=None,
                outputs: Optional[Sequence[str]] = None) -> PlanEpochs:
    """The stream of ``endpoint`` (one server, or several shards: ``"tcp://a:5555,tcp://b:5555"``)
    asking only for ``outputs`` (default: ``task``'s; a run's are ``tasks.stream_outputs(cfg)``),
    by ``v2v_client.plan_dataset.open_stream``: :class:`PlanEpochs` over a
    ``v2v_client.V2VStreamDataset``, in batches of the server's ``batch_size``. ``curve_keys``:
    (client secret key file, server public key file), as in the dataset.

    Raises:
        TimeoutError: no server answered at ``endpoint`` within ``timeout_s``.
        PlanServerError: a server refused or speaks another protocol version (one line).
    """
    return open_stream(endpoint, outputs=tuple(outputs or get_task(task).outputs), raw=bool(raw),
                       timeout_s=float(timeout_s), curve_keys=tuple(curve_keys) if curve_keys else None)


def make_loader(dataset: Iterable, device: torch.device) -> DataLoader:
    """DataLoader over an iterable of ready-made batches (``batch_size=None``), pinning host
    memory when the device is CUDA; no worker processes (the stream client does its own
    network I/O in the background)."""
    return DataLoader(dataset, batch_size=None, num_workers=0, pin_memory=(device.type == "cuda"))


def read_path(stream, device: torch.device):
    """What the training loop iterates for ``stream``: a :class:`ReadAhead` over a plan's epochs
    (:class:`PlanEpochs`), a :func:`make_loader` over any other iterable of batches (a test's
    list of batches, say)."""
    return ReadAhead(stream, pin=device.type == "cuda") if isinstance(stream, PlanEpochs) else make_loader(stream, device)


def close_read_path(path, wait: bool = True) -> None:
    """Stop a read path (or a stream) that has a ``close``. With ``wait`` False (Ctrl-C or SIGTERM),
    a :class:`ReadAhead` is told to stop and left: its thread may be waiting on a silent server
    for the stream's ``timeout_s`` and is a daemon, so the interrupted command ends without it."""
    close = getattr(path, "close", None)
    if isinstance(path, ReadAhead):
        path.close(**({} if wait else {"timeout_s": 0.0}))
    elif callable(close):
        close()


def _to_float(name: str, t: torch.Tensor) -> torch.Tensor:
    """float32 of a stream tensor as its ``outputs.ArraySpec`` says: divided by its
    ``float_divisor`` while still in its integer wire dtype (uint8 frames -> [0, 1]), else the
    value itself (counts, pixels; tensors the client already converted)."""
    spec = ARRAYS.get(name)
    if spec is not None and spec.float_divisor is not None and not t.is_floating_point():
        return t.float().div_(spec.float_divisor)
    return t.float()


def batch_to_device(batch: dict, device: torch.device, outputs: Sequence[str], flow_from: Optional[int] = None) -> dict:
    """Move the ``outputs`` of a stream batch (and its ``voxels``, the models' input) to
    ``device`` with non-blocking copies and convert them to float32 there (``_to_float``).

    With ``flow_from`` given, only ``flow[:, flow_from:]`` is transferred (E2VID's temporal
    consistency loss uses the last part of the sequence only). Copies are non-blocking when the device is CUDA (from pinned memory: ``make_loader``).

    Returns a dict with float32 ``voxels`` (B, L, num_bins, H, W), ``frames`` (B, L+1, 1,
    H, W) in [0, 1], ``flow`` (B, L', 2, H, W) pixels and ``polarity_counts`` (B, L, 2,
    num_bins, H, W), those of ``outputs``.

    Raises:
        KeyError: naming an output of ``outputs`` the batch lacks.
    """
    nb = device.type == "cuda"
    keys = tuple(dict.fromkeys(("voxels", *outputs)))
    for key in outputs:
        if key not in batch:
            raise KeyError(f"stream batch lacks {key!r} (has {sorted(batch)}); the task needs {tuple(outputs)}")
    out = {}
    for key in keys:
        t = batch[key][:, flow_from:] if key == "flow" and flow_from is not None else batch[key]
        out[key] = _to_float(key, t.to(device, non_blocking=nb))
    return out


def drop_padding(batch: dict) -> Tuple[dict, int]:
    """The batch without its padding rows, and how many rows with a sample remain.

    ``batch["padding"]`` (bool (B,), tensor or sequence; optional) marks the rows that hold no
    sample to learn from, which must not enter the loss: in a plan's batch
    (``V2VStreamDataset``) a row without a sample, zeros with sample id None (past the epoch's end,
    or a window the file did not give); in a Ray batch (``v2v_server.ray_data``) a row of a
    window the file did not give, or one of the epoch's first samples listed again so that every
    rank reads as many rows. Tensors and lists whose leading length is B are subset (``padding``
    too); other entries (``epoch``, ``position``) are kept as they are. Without ``padding`` (or
    with none set) the batch is returned unchanged.
    """
    pad = batch.get("padding")
    n = len(batch["voxels"]) if "voxels" in batch else len(batch.get("sample_ids", ()))
    if pad is None:
        return batch, n
    keep = ~torch.as_tensor(pad, dtype=torch.bool).flatten()
    if bool(keep.all()):
        return batch, len(keep)
    idx = keep.nonzero().flatten()
    rows = idx.tolist()
    out = {}
    for k, v in batch.items():
        if isinstance(v, torch.Tensor) and v.ndim >= 1 and v.shape[0] == len(keep):
            out[k] = v[idx]
        elif isinstance(v, Sequence) and not isinstance(v, str) and len(v) == len(keep):
            out[k] = [v[i] for i in rows]
        else:
            out[k] = v
    return out, len(rows)
