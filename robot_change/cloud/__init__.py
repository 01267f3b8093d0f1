"""Depth -> clean cloud: back-projection, voxel grid, outliers, plane, fusion, the chain.

Modules are imported by their full path (the public API is the package face,
:mod:`robot_change`)."""
