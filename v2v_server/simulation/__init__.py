"""The V2V method itself: video frames to the discrete voxel grid (the one kernel, the paper's
equations, refinement and sensor non-idealities feeding it, and the event-based reference)."""
