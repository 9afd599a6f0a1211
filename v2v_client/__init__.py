"""Client side of v2v: ``V2VStreamDataset`` reads batches streamed by ``v2v-serve``."""
from .connection import StreamError, StreamTimeout, batch_to_torch
from .dataset import V2VStreamDataset, dist_position
from .flowgrid import expand_flow_grid
from .loader import StreamLoader

__all__ = ["V2VStreamDataset", "StreamError", "StreamTimeout", "batch_to_torch", "dist_position", "expand_flow_grid",
           "StreamLoader"]
