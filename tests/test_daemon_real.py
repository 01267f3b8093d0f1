"""The daemon (a real ``robot-change run`` subprocess) on a real static room played in a loop:
a hand-held Kinect-class camera's frames of a laptop on a carpet (../shared/data/pcl-grabber-seq,
the camera moving a few millimetres between them).  Nothing in the room changes: every CHECK is
CLEAR and a WATCH never pauses (issue 42: before the camera's noise was measured, a real Kinect
room played this way was answered CHANGED at 7 to 10 of 10 CHECKs).  bench/real_daemon.py runs
it longer: 50 CHECKs and 5 minutes of WATCH."""

from __future__ import annotations

from pathlib import Path

from daemon_rig import Daemon

#: CHECKs the test asks for (each fuses 5 frames of the loop).
CHECKS = 20


def real_room(shared_data: Path) -> str:
    """The looped recording as the daemon's camera."""
    folder = shared_data / "pcl-grabber-seq"
    return (f"images:{folder}?pattern=*_depth.tiff&intrinsics=525,525,320,240&rate=30"
            "&loop=1")


def test_a_real_static_room_in_a_loop_is_always_clear(tmp_path: Path, shared_data) -> None:
    with Daemon(tmp_path, source=real_room(shared_data)) as d:
        d.wait_for("READY=1")
        script = ("capture room\nexpect CAPTURED station=room 20\n"
                  + "check room\nexpect CLEAR station=room 20\n" * CHECKS
                  + "set check_interval_ms 200\nexpect PARAM_VALUE value=200 5\n"
                  + "watch room\nexpect HEARTBEAT state=WATCHING 5\nexpect-none PAUSE 15\n"
                  + "stop\nexpect HEARTBEAT state=IDLE 5\n")
        assert d.base(script, connect_timeout=20) == 0, d.transcript.getvalue()[-3000:]
        got = [e for sim in d.sims for e in sim.log]
        assert not [e for e in got if e.name in ("PAUSE", "REPORT")]
        results = [e.obj for e in got if e.name == "CHECK_RESULT"]
        assert len(results) == CHECKS and all(r.outcome.name == "NO_CHANGE" for r in results)
        captured = next(e.obj for e in got if e.name == "CAPTURED")
        assert captured.noise.startswith("kinect_v1") and captured.smallest_change_mm > 0
