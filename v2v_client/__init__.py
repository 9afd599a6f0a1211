"""Client side of v2v: ``V2VStreamDataset`` reads batches streamed by ``v2v-serve``."""
from .dataset import StreamError, StreamTimeout, V2VStreamDataset, batch_to_torch

__all__ = ["V2VStreamDataset", "StreamError", "StreamTimeout", "batch_to_torch"]
