"""Client side of v2v: ``V2VStreamDataset`` reads the epochs ``v2v-serve`` serves by plan
(docs/delivery.md).

``import v2v_client`` needs only the base install (``pip install v2v``: numpy, pyzmq, msgpack,
PyYAML); the names that make tensors (``V2VStreamDataset``, ``PlanEpochs``, ``ReadAhead``,
``batch_to_torch``, ``expand_flow_grid``, ``prepare_loader``, ``PlanServerError``) import torch
when first used (``pip install 'v2v[client]'``). Names of the push delivery v2v no longer has
(``V2VPushDataset``, ``StreamLoader``, ...) raise ImportError in one line saying what to use
(``v2v_wire.push_names``).
"""
from importlib import import_module

from v2v_wire.push_names import client_name_problem

__all__ = ["V2VStreamDataset", "PlanServerError", "batch_to_torch", "expand_flow_grid", "prepare_loader",
           "PlanEpochs", "ReadAhead"]

#: The public names that need torch, by the module that defines them.
_TORCH_NAMES = {"V2VStreamDataset": "plan_dataset", "PlanServerError": "plan_dataset", "PlanEpochs": "plan_dataset",
                "batch_to_torch": "tensors", "expand_flow_grid": "flowgrid", "prepare_loader": "plan_accelerate",
                "ReadAhead": "read_ahead"}



def __getattr__(name: str):
    """Import a torch-backed public name on first use.

    Raises:
        ImportError: a name of push delivery (one line saying what to use instead), or torch is
            not installed (the message says which install brings it).
        AttributeError: no such name.
    """
    if client_name_problem(name):
        raise ImportError(client_name_problem(name), name=name)
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
