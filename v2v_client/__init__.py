"""Client side of v2v: ``V2VStreamDataset`` reads batches streamed by ``v2v-serve``."""
from .connection import StreamError, StreamTimeout, batch_to_torch
from .dataset import V2VStreamDataset
from .flowgrid import expand_flow_grid

__all__ = ["V2VStreamDataset", "StreamError", "StreamTimeout", "batch_to_torch", "expand_flow_grid"]
