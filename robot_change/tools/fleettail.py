"""``robot-change fleet-tail``: the fleet's changes and status as they come, one line each (or
one JSON object a line with ``--json``), for operators and tests
(robot_change.fleet.receiver underneath)."""

from __future__ import annotations

import sys
import threading
import time
from typing import Any, TextIO

from robot_change import json_text
from robot_change.errors import FleetError
from robot_change.fleet.connection import BrokerSettings
from robot_change.fleet.receiver import Incoming, Receiver

__all__ = ["describe", "run_fleet_tail"]

#: The broker's errors name the daemon's keys; here they are fleet-tail's options.
_OPTIONS = {"fleet.ca_file": "--ca-file", "fleet.cert_file": "--cert-file",
            "fleet.key_file": "--key-file", "fleet.username": "--username",
            "fleet.password_file": "--password-file"}


def _in_options(text: str) -> str:
    for key, option in _OPTIONS.items():
        text = text.replace(key, option)
    return text


def _when(payload: dict[str, Any]) -> str:
    text = payload.get("time")
    if isinstance(text, str) and "T" in text:
        return text.split("T", 1)[1].rstrip("Z")
    return time.strftime("%H:%M:%S", time.gmtime()) + " (arrival)"


def _status(robot: str, p: dict[str, Any]) -> str:
    if not p.get("online", True):
        return f"{robot} OFFLINE ({p.get('reason', '?')})"
    camera = p.get("camera") or {}
    fleet = p.get("fleet") or {}
    spool = fleet.get("spool") or {}
    last = p.get("last_check") or {}
    flags = [p.get("state", "?")] + (["PAUSED"] if p.get("paused") else []) + (
        [] if p.get("armed", True) else ["disarmed"])
    text = (f"{robot} online: {' '.join(flags)}"
            + (f", station {p['station']}" if p.get("station") else "")
            + ("; camera ok" if camera.get("ok") else f"; camera LOST ({camera['error']})"
               if camera.get("error") else "; camera opening")
            + f"; link {(p.get('link') or {}).get('state', '?')}")
    if last:
        text += f"; last check {last.get('outcome')} at {last.get('station')}"
    dropped = int(spool.get("dropped", 0)) + int(fleet.get("queue_dropped", 0))
    text += f"; spool {spool.get('queued', 0)}" + (f", {dropped} DROPPED" if dropped else "")
    faults = p.get("faults") or []
    if faults:
        text += f"; last fault {faults[-1].get('code')}: {faults[-1].get('text')}"
    return text


def _change(robot: str, station: str, p: dict[str, Any]) -> str:
    regions = p.get("regions") or []
    offset = p.get("offset_base") or {}
    lines = [f"{robot} CHANGED {station}: {len(regions)} region(s) ({p.get('origin')}, report "
             f"{p.get('report_id')})"]
    if offset.get("translation_m"):
        lines[0] += ("; robot offset " + " ".join(
            f"{a} {v * 100:+.1f} cm" for a, v in zip("xyz", offset["translation_m"], strict=False))
            + " yaw " + f"{offset.get('rpy_deg', [0, 0, 0])[2]:+.1f} deg")
    for region in regions:
        base = region.get("base") or {}
        x, y, z = base.get("centroid_m", [0, 0, 0])
        extent = " x ".join(f"{v:.2f}" for v in base.get("extent_m", []))
        lines.append(f"    {region.get('kind', '?'):11s} {region.get('n_points', 0):6d} points "
                     f"at {x:.2f} m ahead, {y:+.2f} m left, {z:+.2f} m up; extent {extent} m")
    return "\n".join(lines)


def describe(m: Incoming) -> str:
    """One message as text (a change: a line per region); a message that is not what the
    fleet sends is said to be so, never a traceback."""
    if m.error:
        return f"{m.robot} {m.kind}: unreadable message on {m.topic}: {m.error}"
    try:
        return _describe(m)
    except (AttributeError, TypeError, ValueError, KeyError, IndexError) as exc:
        return (f"{m.robot} {m.kind}: unexpected message on {m.topic} ({type(exc).__name__}: "
                f"{exc}): {json_text.dumps(m.payload)[:200]}")


def _describe(m: Incoming) -> str:
    p = m.payload
    if m.kind == "status":
        return _status(m.robot, p)
    if m.kind == "changes":
        return _change(m.robot, m.station, p)
    if m.kind == "checks":
        report = p.get("report") or {}
        return (f"{m.robot} check {m.station}: {report.get('outcome')} ({p.get('origin')}, "
                f"report {p.get('report_id')})")
    if "error" in p:
        return f"{m.robot} reply to {p.get('id')!r}: refused: {p['error']}"
    return f"{m.robot} reply to {p.get('id')!r}: " + _status(m.robot, p.get("status") or {})


def run_fleet_tail(settings: BrokerSettings, *, prefix: str, robot: str, checks: bool,
                   as_json: bool, session: str | None, count: int | None,
                   seconds: float | None, out: TextIO = sys.stdout) -> int:
    """Print the fleet's messages until ``count`` were printed, ``seconds`` passed, or Ctrl-C.
    Raises FleetError when the first connection fails."""
    stop = threading.Event()
    printed = [0]

    def show(m: Incoming) -> None:
        if as_json:
            line = json_text.dumps({"topic": m.topic, "robot": m.robot, "kind": m.kind,
                               "station": m.station, "message": m.payload,
                               **({"error": m.error} if m.error else {})})
        else:
            line = f"{_when(m.payload)} {describe(m)}"
        print(line, file=out, flush=True)
        printed[0] += 1
        if count is not None and printed[0] >= count:
            stop.set()

    def state(text: str) -> None:
        print(f"robot-change fleet-tail: {_in_options(text)}", file=sys.stderr, flush=True)

    receiver = Receiver(settings, show, prefix=prefix, robot=robot, checks=checks,
                        session=session, on_state=state)
    if seconds is not None:
        timer = threading.Timer(seconds, stop.set)
        timer.daemon = True
        timer.start()
    try:
        receiver.run(stop)
    except FleetError as exc:
        raise FleetError(_in_options(str(exc)), transient=exc.transient) from None
    if receiver.duplicates:
        state(f"{receiver.duplicates} duplicate report message(s) dropped (same report id)")
    return 0
