"""Optical flow between video frames: the flow options (``options.py``), the estimator every
option runs through (``estimate.py``: DIS, the tracked grid, RAFT) and the grid tracker
(``tracking.py``). Below the simulation (refinement and the event-level reference use DIS) and the
sample cutter (the flow between voxel boundaries); imports nothing of the server's other stages."""
