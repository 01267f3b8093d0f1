"""Gaussian mixtures: the EM kernels, the model and its file, split-EM stopped by MDL.

Modules are imported by their full path (the public API is the package face,
:mod:`robot_change`)."""
