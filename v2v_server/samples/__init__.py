"""Cutting a decoded video into samples: windows, crops, flips, pauses and sensor parameters drawn
from (seed, epoch, sample id), the ablation switches, and each sample's outputs (V2V from
``simulation``, the optical flow between voxel boundaries from ``flow``)."""
