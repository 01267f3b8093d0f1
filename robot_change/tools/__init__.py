"""Tools around the module: the simulated base, the link bench, the demo, benchmarks, pictures.

Modules are imported by their full path (the public API is the package face,
:mod:`robot_change`)."""
