"""The commands around the daemon that do not run it: ``warm-up`` (the numba kernels
compiled into the cache), ``check-config`` (a configuration read and checked) and ``demo``
(the daemon and a simulated base on a bundled recording).  ``run`` itself stays in
robot_change.cli, the one place that opens the camera and the serial port."""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from robot_change.commands.common import SIM_FIXTURES, _print_json


def cmd_demo(args: argparse.Namespace) -> int:
    """The README's main job on a bundled recording: the real daemon in a subprocess, the
    simulated base on a pty pair; capture a reference, the scene changes, check, PAUSE and
    CHANGE_REPORT, and report.png of what changed (robot_change.tools.demo)."""
    from robot_change.tools.demo import run_demo

    return run_demo(Path(args.out), SIM_FIXTURES)


def cmd_warm_up(args: argparse.Namespace) -> int:
    """Compile the numba kernels into the cache (NUMBA_CACHE_DIR, else beside the package), so
    that the next start of the daemon or of a command loads them instead."""
    from robot_change.service.warmup import warm_up

    seconds = warm_up()
    where = os.environ.get("NUMBA_CACHE_DIR") or "the package's __pycache__ folders"
    print(f"kernels ready in {seconds:.1f} s (cache: {where})")
    return 0


def cmd_check_config(args: argparse.Namespace) -> int:
    """Read and check a configuration file; print the effective settings."""
    from robot_change.service.params import load_checked_config

    config = load_checked_config(args.file)
    if args.json:
        _print_json(config.as_dict())
    else:
        print(f"# {args.file}: OK; the effective settings (defaults included):")
        print(config.as_toml(), end="")
        for note in _absent_now(config):
            print(f"# note: {note}")
    return 0


def _absent_now(config) -> list[str]:
    """What the configuration names on this machine that is not there now: a recording or
    folder the camera source reads (the daemon answers CAMERA_LOST until it is), the serial
    port (it waits for it).  Not errors: a USB adapter or a mounted disk may come later."""
    from hw.depth import parse_uri

    notes = []
    scheme, target, _ = parse_uri(config.camera.source)
    if scheme not in ("openni2", "realsense") and not Path(target).exists():
        notes.append(f"camera.source: {target} does not exist now (the daemon reports "
                     "CAMERA_LOST until it does)")
    port = str(config.serial.port)
    if "://" not in port and not Path(port).exists():
        notes.append(f"serial.port: {port} does not exist now (the daemon waits for it)")
    if config.fleet.enabled and config.fleet.settings().cleartext_warning():
        notes.append(f"fleet.broker: {config.fleet.settings().cleartext_warning()}")
    return notes
