"""``robot-change demo``: the whole job end to end, without hardware.

The real daemon (``robot-change run``) runs as a subprocess on a bundled recording of an office
(played in a loop at 30 fps, like a camera); the simulated base controller talks to it over a
pty pair (one end each, like a USB serial cable).  The base captures a reference; the camera is
switched to the recording of the same office with a box added (a SIGHUP with a configuration
whose camera.source changed: the daemon reopens its camera); the base checks; the daemon pauses
the base and reports what changed; the base resumes; the daemon stops on SIGTERM.

Files in ``--out``: ``report.png`` (what changed), ``robot-change.toml`` (the daemon's
configuration), ``daemon.log`` (its log), ``base.log`` (every message the base saw), ``state/``
(the stored reference, the last check, and with foxglove-sdk each CHECK as an MCAP file for
Foxglove in ``state/reports/checks/``).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import tty
from pathlib import Path
from typing import Any, TextIO

from hw.serial_port import FdPort
from robot_change import npzfile
from robot_change.change.detect import detect_changes
from robot_change.errors import InputError, RobotChangeError
from robot_change.link.protocol import ModuleState, describe
from robot_change.service.config import load_config
from robot_change.service.core import CHECK_FORMAT
from robot_change.service.params import change_params
from robot_change.service.store import ReferenceStore
from robot_change.tools.basesim import BaseSim

SCENE = "office_box_added"
STATION = "office"


def _toml(source: str, port: str, state: Path) -> str:
    return (f'[camera]\nsource = {json.dumps(source)}\n\n'
            f'[serial]\nport = {json.dumps(port)}\n\n'
            f'[store]\nstate_dir = {json.dumps(str(state))}\n\n'
            '[service]\nwatchdog = false\nlog_level = "info"\n')


def _say(out: TextIO, text: str) -> None:
    print(text, file=out, flush=True)


def run_demo(out_dir: Path, fixtures: Path, *, out: TextIO | None = None,
             start_timeout: float = 300.0) -> int:
    """Run the demo (module docstring); 0 when the base saw CAPTURED, PAUSE and the report."""
    out = out or sys.stdout
    scene_dir = fixtures / "scenes" / SCENE
    reference, current = scene_dir / "reference.oni", scene_dir / "current.oni"
    if not reference.is_file() or not current.is_file():
        raise InputError(f"the bundled recordings {reference} and {current} are missing: they "
                         "ship with robot-change (sim_fixtures); reinstall it")
    truth = json.loads((scene_dir / "scene.json").read_text()).get("description", "")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    state = (out_dir / "state").resolve()
    config = out_dir / "robot-change.toml"
    master, slave = os.openpty()
    tty.setraw(master)
    tty.setraw(slave)
    port_path = os.ttyname(slave)
    camera = f"oni:{reference}?loop=1&rate=auto"
    config.write_text(_toml(camera, port_path, state))
    log_file = open(out_dir / "daemon.log", "w")
    base_log = open(out_dir / "base.log", "w")
    command = [sys.executable, "-m", "robot_change.cli", "run", "--config", str(config)]
    t0 = time.monotonic()
    daemon = subprocess.Popen(command, stdout=log_file, stderr=subprocess.STDOUT,
                              stdin=subprocess.DEVNULL)
    code = 1
    try:
        sim = BaseSim(FdPort(master), out=base_log)
        _say(out, "robot-change demo: the daemon on a recorded office, a simulated base on a "
                  "pty pair")
        _say(out, f"  daemon  robot-change run --config {config}  (pid {daemon.pid})")
        _say(out, f"  camera  {reference.relative_to(fixtures.parent)} (looped at 30 fps)")
        _say(out, f"  line    {port_path} <-> the base")
        def booted() -> bool:  # the link is up and the heartbeats no longer say BOOTING
            beats = [e.obj.state for e in sim.log if e.name == "HEARTBEAT"]
            return (sim.link.state.value == "up" and bool(beats)
                    and beats[-1] != ModuleState.BOOTING) or daemon.poll() is not None

        up = sim.pump(5.0, until=booted)
        if not up:
            _say(out, "  (waiting for the daemon: a first run compiles the numba kernels, which "
                      "takes a minute or two, its heartbeats saying BOOTING; later runs load "
                      "them from the cache)")
            up = sim.pump(start_timeout, until=booted)
        if not up or daemon.poll() is not None:
            _say(out, f"FAIL: the daemon did not answer (see {out_dir / 'daemon.log'})")
            return 1
        _say(out, f"  module idle {time.monotonic() - t0:.1f} s after start "
                  "(kernels loaded, camera open)\n")

        def send(line: str) -> float:
            sim.command(line)
            _say(out, f"base -> {line.split()[0].upper()} {' '.join(line.split()[1:])}".rstrip())
            return time.monotonic()

        def expect(what: str, seconds: float, **filters: str) -> Any:
            entry = sim.expect(what, filters, seconds)
            if entry is None:
                raise _Failed(f"no {what} within {seconds:g} s (see {out_dir / 'base.log'} and "
                              f"{out_dir / 'daemon.log'})")
            return entry

        def show(entry: Any, since: float) -> None:
            _say(out, f"base <- {describe(entry.obj)}   ({(entry.t - since) * 1000:.0f} ms)")

        try:
            sent = send(f"capture {STATION}")
            show(expect("CAPTURED", 20.0), sent)
            # the scene changes: point the camera at the other recording, reload with SIGHUP
            config.write_text(_toml(f"oni:{current}?loop=1&rate=auto", port_path, state))
            daemon.send_signal(signal.SIGHUP)
            _say(out, f"\n  (a box is put in the room: the camera now plays {current.name}; "
                      "config reloaded by SIGHUP)\n")
            start = len(sim.log)

            def reopened() -> bool:  # the new recording counts its frames from 1 again
                beats = [e.obj.frame_index for e in sim.log[start:] if e.name == "HEARTBEAT"]
                return any(b < a for a, b in zip(beats, beats[1:], strict=False))

            sim.pump(10.0, until=reopened)
            sim.cursor = len(sim.log)
            sent = send(f"check {STATION}")
            show(expect("PAUSE", 20.0), sent)
            report = expect("REPORT", 5.0)
            for part in (e for e in sim.log if e.name == "CHANGE_REPORT"
                         and e.obj.report_id == report.obj.report_id):
                show(part, sent)
            for region in report.obj.regions:
                x, y, z = region.centroid_mm
                dx, dy, dz = region.extent_mm
                _say(out, f"          {region.kind.name.lower()}: {dx / 10:.0f} x {dy / 10:.0f} x "
                          f"{dz / 10:.0f} cm, centre ({x}, {y}, {z}) mm, {region.points} points")
            if truth:
                _say(out, f"          (the truth: {truth})")
            expect("BASE", 2.0, paused="1")
            _say(out, "base    stopped: the module's pause latch is set")
            sent = send("resume")
            show(expect("HEARTBEAT", 2.0, paused="0"), sent)
            _say(out, "base    may move again")
            code = 0
        except _Failed as exc:
            _say(out, f"FAIL: {exc}")
        daemon.send_signal(signal.SIGTERM)
        try:
            status = daemon.wait(15.0)
        except subprocess.TimeoutExpired:
            daemon.kill()
            status = daemon.wait(5.0)
            code = 1
        _say(out, f"\n  daemon stopped by SIGTERM, exit status {status}")
        if status != 0:
            code = 1
        if code == 0:
            picture = _picture(state, out_dir, config)
            _say(out, f"wrote {picture} (what changed), {out_dir / 'base.log'}, "
                      f"{out_dir / 'daemon.log'}")
            for view in sorted((state / "reports" / "checks").glob("*.mcap"))[-1:]:
                _say(out, f"the check in 3-D: open {view} in Foxglove (docs/ros.md)")
        return code
    finally:
        if daemon.poll() is None:
            daemon.kill()
            daemon.wait(5.0)
        log_file.close()
        base_log.close()
        os.close(slave)
        os.close(master)


class _Failed(Exception):
    pass


def _picture(state: Path, out_dir: Path, config: Path) -> Path:
    """report.png of the daemon's last check: its fused depth (saved by the daemon in
    state/reports/) compared again with the stored reference, with the same parameters (the
    detection is seeded, so the picture shows what the daemon found), drawn by
    :func:`robot_change.tools.report.draw_change`."""
    from robot_change.tools.report import (
        draw_change,  # matplotlib: the optional viz extra
    )

    settings = load_config(config)
    _header, saved = npzfile.read(state / "reports" / f"{STATION}.last-check.npz",
                                  CHECK_FORMAT, 1, ["depth"], RobotChangeError,
                                  "run the demo again")
    reference = ReferenceStore(state / "references").load(STATION)
    depth = saved["depth"]
    changes = detect_changes(reference, depth, change_params(settings, settings.parameters()))
    return draw_change(reference.depth, depth, reference.intrinsics, changes,
                       out_dir / "report.png", title=f"station {STATION!r}")


__all__ = ["run_demo"]
