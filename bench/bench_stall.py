"""How long from a hang to the base's FAULT, to its PAUSE, to the last watchdog ping and to
the daemon's exit (systemd then restarts it after RestartSec=2); and SIGTERM to exit.

    .venv/bin/python bench/bench_stall.py [--runs 3] [--watchdog-sec 10] [--json OUT]

The real daemon (tests/daemon_rig.py: a subprocess, an image folder as the camera, the
simulated base on a pty pair, a test socket as systemd's notify socket) with a hang injected
(tests/hang_daemon.py) into the WATCH detector, a CHECK, a capture or a camera read, with the
unit's WatchdogSec (stall bound: half of it).  Medians and maxima over ``--runs`` per kind.
docs/benchmarks.md ("Watchdog") reports its output.  A benchmark, never a test.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from daemon_rig import WATCH_SETUP as SETUP  # noqa: E402
from daemon_rig import Daemon  # noqa: E402

from robot_change.link.protocol import FaultCode, PauseCause  # noqa: E402


def one(kind: str, watchdog_sec: float) -> dict:
    with tempfile.TemporaryDirectory() as tmp, \
            Daemon(Path(tmp), hang=kind, watchdog_usec=int(watchdog_sec * 1e6)) as d:
        d.wait_for("READY=1")
        timeout = watchdog_sec + 10
        if kind in ("detector", "camera"):
            _thread, result = d.base_in_thread(SETUP + f"expect FAULT code=STALLED {timeout}")
            d.wait_for("WATCH office:")
            time.sleep(1.0)
            d.arm()
        else:
            d.arm()
            first = "" if kind == "capture" else "capture office\nexpect CAPTURED 10\n"
            _thread, result = d.base_in_thread(
                first + f"{'capture' if kind == 'capture' else 'check'} office\n"
                f"expect FAULT code=STALLED {timeout}")
        entered = d.wait_entered(timeout)
        code = d.proc.wait(timeout + 10)
        ended = time.monotonic()
        _thread.join(10)
        fault = d.first("FAULT", code=FaultCode.STALLED)
        pause = d.first("PAUSE", cause=PauseCause.INTERNAL_ERROR)
        pings = d.pings(after=d.started)
        last_ping = max(pings) if pings else None
    return {"kind": kind, "exit": code, "base_ok": result == [0],
            "hang_to_fault_s": None if fault is None else round(fault - entered, 3),
            "hang_to_pause_s": None if pause is None else round(pause - entered, 3),
            "hang_to_last_ping_s": None if last_ping is None else round(last_ping - entered, 3),
            "hang_to_exit_s": round(ended - entered, 3)}


def sigterm(state: str) -> float:
    with tempfile.TemporaryDirectory() as tmp, \
            Daemon(Path(tmp), hang="detector" if state == "hung detector" else None) as d:
        d.wait_for("READY=1")
        if state != "idle":
            _thread, _ = d.base_in_thread(SETUP + "wait 4")
            d.wait_for("WATCH office:")
            if state == "hung detector":
                d.arm()
                d.wait_entered()
            time.sleep(0.5)
        _code, seconds = d.terminate()
        return seconds


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--watchdog-sec", type=float, default=10.0)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    rows = []
    for run in range(args.runs):
        for kind in ("detector", "check", "capture", "camera"):
            row = one(kind, args.watchdog_sec)
            row["run"] = run
            rows.append(row)
            print(json.dumps(row), flush=True)
    summary = {}
    for kind in ("detector", "check", "capture", "camera"):
        sel = [r for r in rows if r["kind"] == kind]
        summary[kind] = {key: {"median": statistics.median(r[key] for r in sel),
                               "max": max(r[key] for r in sel)}
                         for key in ("hang_to_fault_s", "hang_to_exit_s")
                         if all(r[key] is not None for r in sel)}
        summary[kind]["exits"] = sorted({r["exit"] for r in sel})
    terms = {state: [sigterm(state) for _ in range(args.runs)]
             for state in ("idle", "watching", "hung detector")}
    summary["sigterm_s"] = {s: {"median": statistics.median(v), "max": max(v)}
                            for s, v in terms.items()}
    machine = {"python": platform.python_version(), "cores": os.cpu_count(),
               "load": [round(v, 2) for v in os.getloadavg()],
               "watchdog_sec": args.watchdog_sec}
    print(json.dumps({"summary": summary, "machine": machine}, indent=1))
    if args.json:
        args.json.write_text(json.dumps({"rows": rows, "summary": summary, "machine": machine},
                                        indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
