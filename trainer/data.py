"""Stream side of the trainer: which outputs each task asks ``v2v-serve`` for, the
DataLoader around ``v2v_client.V2VStreamDataset`` (a push server) or ``V2VPlanDataset`` read
epoch after epoch (a server serving by plan: :class:`PlanEpochs`), and the host -> device transfer.

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

from v2v_wire.outputs import ARRAYS

from .tasks import get_task

__all__ = ["make_stream", "PlanEpochs", "make_loader", "batch_to_device", "drop_padding"]


def make_stream(endpoint: str, task: str, credits: int = 4, timeout_s: float = 60.0, raw: bool = True,
                reconnect: bool = False, curve_keys=None, outputs: Optional[Sequence[str]] = None,
                compact_flow: bool = True):
    """Open a ``v2v_client.V2VStreamDataset`` on ``endpoint`` (one server, or several:
    ``"tcp://a:5555,tcp://b:5555"``) asking only for ``outputs`` (default: ``task``'s; a run's
    are ``tasks.stream_outputs(cfg)``); ``reconnect``, ``compact_flow`` (a tracked flow
    arrives as its grid, made dense on the training device by :func:`batch_to_device`) and
    ``curve_keys`` (client secret key file, server public key file) as in the dataset. A single
    server serving by plan (it says so when asked) is read by :class:`PlanEpochs` instead, in
    batches of the server's ``batch_size``.
    Raises ``ImportError`` with a hint when the client is not installed."""
    try:
        from v2v_client import V2VPlanDataset, V2VStreamDataset
        from v2v_client.plan_dataset import PlanServerError
    except ImportError as e:  # pragma: no cover - depends on the installed client
        raise ImportError("v2v_client.V2VStreamDataset is not available; install the v2v "
                          "client (pip install -e '.[client]')") from e
    keys = tuple(curve_keys) if curve_keys else None
    plan_args = {"timeout_s": float(timeout_s), "retry_s": min(10.0, float(timeout_s)), "curve_keys": keys}
    if "," not in endpoint:  # several servers fan in by push only
        try:
            info = V2VPlanDataset(endpoint, 1, **plan_args).plan_info()
        except (PlanServerError, TimeoutError):  # a push server answered, or none did: the push client says so
            info = None
        if info is not None:
            return PlanEpochs(V2VPlanDataset(endpoint, int(info.stream.get("batch_size", 1)),
                                             outputs=tuple(outputs or get_task(task).outputs), raw=bool(raw),
                                             **plan_args))
    return V2VStreamDataset(endpoint=endpoint, outputs=tuple(outputs or get_task(task).outputs), credits=int(credits),
                            timeout_s=float(timeout_s), raw=bool(raw), reconnect=bool(reconnect),
                            curve_keys=tuple(curve_keys) if curve_keys else None, compact_flow=bool(compact_flow))


class PlanEpochs(torch.utils.data.IterableDataset):
    """``v2v-train``'s one pass over a plan: the epochs of a ``V2VPlanDataset`` in turn (each
    ``set_epoch`` after the last), from the epoch of a loaded position on. :meth:`state_dict` /
    :meth:`load_state_dict` are the dataset's (a position: the epoch and the samples read).
    An epoch without a batch ends the pass."""

    def __init__(self, dataset):
        super().__init__()
        self.dataset = dataset

    def __iter__(self):
        while True:
            last = None
            for batch in self.dataset:
                last = batch["epoch"]
                yield batch
            if last is None:
                return
            self.dataset.set_epoch(last + 1)

    def state_dict(self) -> dict:
        return self.dataset.state_dict()

    def load_state_dict(self, state: dict) -> None:
        self.dataset.load_state_dict(state)


def make_loader(dataset: Iterable, device: torch.device) -> DataLoader:
    """DataLoader over an iterable of ready-made batches (``batch_size=None``), pinning host
    memory when the device is CUDA; no worker processes (the stream client does its own
    network I/O in the background)."""
    return DataLoader(dataset, batch_size=None, num_workers=0, pin_memory=(device.type == "cuda"))


def _to_float(name: str, t: torch.Tensor) -> torch.Tensor:
    """float32 of a stream tensor as its ``outputs.ArraySpec`` says: divided by its
    ``float_divisor`` while still in its integer wire dtype (uint8 frames -> [0, 1]), else the
    value itself (counts, pixels; tensors the client already converted)."""
    spec = ARRAYS.get(name)
    if spec is not None and spec.float_divisor is not None and not t.is_floating_point():
        return t.float().div_(spec.float_divisor)
    return t.float()


def _array_for(batch: dict, output: str) -> Optional[str]:
    """The batch array that carries ``output``: its own, else a compact form of it
    (``outputs.ArraySpec.expand``: ``flow_grid`` for ``flow``); None when the batch has neither."""
    if output in batch:
        return output
    return next((s.name for s in ARRAYS.values() if s.output == output and s.expand and s.name in batch), None)


def batch_to_device(batch: dict, device: torch.device, outputs: Sequence[str], flow_from: Optional[int] = None) -> dict:
    """Move the ``outputs`` of a stream batch (and its ``voxels``, the models' input) to
    ``device`` with non-blocking copies and convert them to float32 there (``_to_float``).

    With ``flow_from`` given, only ``flow[:, flow_from:]`` is transferred (E2VID's temporal
    consistency loss uses the last part of the sequence only). A batch with ``flow_grid``
    (B, L, 2, n, n) in place of ``flow`` (``compact_flow``) has the grid transferred and made
    dense on the device (``v2v_client.expand_flow_grid``, the crop size of the voxels).
    Copies are non-blocking when the device is CUDA (from pinned memory: ``make_loader``).

    Returns a dict with float32 ``voxels`` (B, L, num_bins, H, W), ``frames`` (B, L+1, 1,
    H, W) in [0, 1], ``flow`` (B, L', 2, H, W) pixels and ``polarity_counts`` (B, L, 2,
    num_bins, H, W), those of ``outputs``.

    Raises:
        KeyError: naming an output of ``outputs`` the batch lacks.
    """
    nb = device.type == "cuda"
    names = {key: _array_for(batch, key) for key in dict.fromkeys(("voxels", *outputs))}
    for key in outputs:
        if names[key] is None:
            raise KeyError(f"stream batch lacks {key!r} (has {sorted(batch)}); the task needs {tuple(outputs)}")
    out = {}
    for key, name in names.items():
        t = batch[name][:, flow_from:] if key == "flow" and flow_from is not None else batch[name]
        t = _to_float(name, t.to(device, non_blocking=nb))
        if ARRAYS[name].expand:  # a compact form (flow_grid): made dense on the device
            from v2v_client import expand_flow_grid

            t = expand_flow_grid(t, tuple(out["voxels"].shape[-2:]))
        out[key] = t
    return out


def drop_padding(batch: dict) -> Tuple[dict, int]:
    """The batch without its padding samples, and how many real samples remain.

    ``batch["padding"]`` (bool (B,), tensor or sequence; optional) marks samples repeated only
    to give every DDP rank the same batch count: they must not enter the loss. Tensors and
    lists whose leading length is B are subset; other entries (``epoch``, ``batch_id``) are
    kept as they are. Without ``padding`` (or with none set) the batch is returned unchanged.
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
