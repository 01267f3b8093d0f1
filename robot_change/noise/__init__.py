"""Depth camera noise: the profile every decision of a check is scaled by
(:mod:`robot_change.noise.profile`), its measurement from a still camera's frames
(:mod:`robot_change.noise.estimate`) and its reading inside numba kernels
(:mod:`robot_change.noise.kernels`); what a station can see with it is
:mod:`robot_change.change.limits`.  Numeric; imports only the top-level helpers and hw."""
