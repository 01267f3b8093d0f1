"""Comparing an epoch with the station's reference: the reference model (SceneModel),
registration, the camera's mounting, EMD, change detection.

Modules are imported by their full path (the public API is the package face,
:mod:`robot_change`)."""
