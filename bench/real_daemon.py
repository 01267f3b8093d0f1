"""The daemon on real static rooms played in a loop: how many CHECKs are answered CHANGED (must
be 0) and whether a WATCH of some minutes ever pauses (must not).

    .venv/bin/python bench/real_daemon.py [--checks 50] [--watch-s 300] [--heldout DIR]
        [--json OUT]

The real daemon (tests/daemon_rig.py: a subprocess, the simulated base on a pty pair) reads a
looped image folder as its camera: the hand-held Kinect-class frames of
../shared/data/pcl-grabber-seq (3 frames, a few millimetres apart), and with ``--heldout`` the
first 10 frames of the 7-Scenes kitchen (a Kinect v1 nearly still, 2-5 mm apart; outside the
repository, never tuned on).  The base captures the station, asks ``--checks`` CHECKs, then
WATCHes it for ``--watch-s`` seconds, the daemon's checks every 200 ms.  docs/evaluation.md
reports its output.  A benchmark, never a test (tests/test_daemon_real.py runs a short one).
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from daemon_rig import Daemon  # noqa: E402

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"


def rooms(heldout: Path | None) -> dict[str, str]:
    """name -> the looped depth URI of each real static room."""
    out = {"pcl-grabber (Kinect-class, hand-held)":
           f"images:{SHARED / 'pcl-grabber-seq'}?pattern=*_depth.tiff"
           "&intrinsics=525,525,320,240&rate=30&loop=1"}
    if heldout is not None:
        kitchen = heldout / "7scenes-redkitchen-kinect-100f-pose" / "frames"
        out["7-Scenes kitchen (Kinect v1, held out)"] = (
            f"images:{kitchen}?pattern=frame-00000[0-9].depth.png"
            "&intrinsics=585,585,320,240&rate=30&loop=1")
    return out


def one(name: str, source: str, checks: int, watch_s: float) -> dict:
    with tempfile.TemporaryDirectory() as tmp, Daemon(Path(tmp), source=source) as d:
        d.wait_for("READY=1")
        t0 = time.monotonic()
        code = d.base("capture room\nexpect CAPTURED station=room 30\n"
                      + "check room\nexpect CHECK_RESULT station=room 30\n" * checks,
                      connect_timeout=30)
        checked = time.monotonic() - t0
        code_watch = d.base("set check_interval_ms 200\nexpect PARAM_VALUE value=200 5\n"
                            f"watch room\nexpect HEARTBEAT state=WATCHING 5\nwait {watch_s}\n"
                            "stop\nexpect HEARTBEAT state=IDLE 10\n", connect_timeout=30)
        got = [e for sim in d.sims for e in sim.log]
        outcomes = [e.obj.outcome.name for e in got if e.name == "CHECK_RESULT"]
        watch_checks = d.log().count("WATCH room:")
        captured = next((e.obj for e in got if e.name == "CAPTURED"), None)
        return {"room": name, "scripts_ok": code == 0 and code_watch == 0,
                "checks": len(outcomes), "changed": outcomes.count("CHANGED"),
                "not_at_station": outcomes.count("NOT_AT_STATION"),
                "pauses": sum(e.name == "PAUSE" for e in got),
                "reports": sum(e.name == "REPORT" for e in got),
                "watch_s": watch_s, "watch_log_lines": watch_checks,
                "check_s_mean": round(checked / max(len(outcomes), 1), 2),
                "noise": getattr(captured, "noise", None),
                "smallest_change_mm": getattr(captured, "smallest_change_mm", None)}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--checks", type=int, default=50)
    ap.add_argument("--watch-s", type=float, default=300.0)
    ap.add_argument("--heldout", type=Path, nargs="?", const=Path("/work/heldout-data"))
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    report = {"machine": {"python": platform.python_version(), "platform": platform.platform()},
              "rooms": [one(n, s, args.checks, args.watch_s)
                        for n, s in rooms(args.heldout).items()]}
    for r in report["rooms"]:
        print(json.dumps(r), flush=True)
    if args.json:
        args.json.write_text(json.dumps(report, indent=1))
    return report


if __name__ == "__main__":
    main()
