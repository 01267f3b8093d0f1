"""The daemon: state machine, camera thread, WATCH, liveness, reference store, configuration,
systemd, warm-up, main loop.

Modules are imported by their full path (the public API is the package face,
:mod:`robot_change`)."""
