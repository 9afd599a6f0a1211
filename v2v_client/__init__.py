"""Client side of v2v: ``V2VStreamDataset`` reads the epochs ``v2v-serve`` serves by plan
(docs/plan.md); ``V2VPushDataset`` reads a server started with ``--delivery push``.

``import v2v_client`` and its network side (``connection``, ``session``: a server's batches as
numpy arrays) need only the base install (``pip install v2v``: numpy, pyzmq, msgpack, PyYAML);
the names that make tensors (``V2VStreamDataset``, ``V2VPushDataset``, ``StreamLoader``,
``batch_to_torch``, ``expand_flow_grid``, ``dist_position``, ``prepare_loader``, ``PlanEpochs``,
``ReadAhead``) import torch when
first used (``pip install 'v2v[client]'``).
"""
from importlib import import_module

from .session import StreamError, StreamTimeout

__all__ = ["V2VStreamDataset", "V2VPushDataset", "PlanServerError", "PushServerError", "StreamError", "StreamTimeout",
           "batch_to_torch", "dist_position", "expand_flow_grid", "StreamLoader", "prepare_loader", "PlanEpochs", "ReadAhead"]

#: The public names that need torch, by the module that defines them.
_TORCH_NAMES = {"V2VPushDataset": "dataset", "V2VStreamDataset": "plan_dataset", "dist_position": "dataset",
                "batch_to_torch": "tensors", "PlanServerError": "plan_dataset", "PushServerError": "plan_dataset",
                "expand_flow_grid": "flowgrid", "StreamLoader": "loader",
                "prepare_loader": "launchers", "PlanEpochs": "plan_dataset", "ReadAhead": "read_ahead"}


def __getattr__(name: str):
    """Import a torch-backed public name on first use.

    Raises:
        ImportError: torch is not installed (the message says which install brings it).
        AttributeError: no such name.
    """
    module = _TORCH_NAMES.get(name)
    if module is None:
        raise AttributeError(f"module 'v2v_client' has no attribute {name!r}")
    try:
        value = getattr(import_module(f".{module}", __name__), name)
    except ModuleNotFoundError as e:
        if e.name != "torch":
            raise
        raise ImportError(f"v2v_client.{name} needs torch, which is not installed: pip install 'v2v[client]' "
                          "(or torch first, see README)", name="torch") from e
    globals()[name] = value
    return value
