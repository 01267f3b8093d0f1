"""The real daemon under faults (a subprocess; tests/daemon_rig.py): injected hangs reach the
base as FAULT STALLED (and PAUSE while watching), the watchdog stops being fed and the process
exits 70 for systemd to restart it; SIGTERM ends it within 2 s in every state, a cold compile
and a hung kernel included, with no READY after STOPPING; a cold start talks (BOOTING) while
it compiles; ``check-config`` and ``run`` refuse
the same files the same way, and a refused reload keeps the old configuration and says so."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from daemon_rig import REPO, WATCH_SETUP, Daemon

from robot_change.link.protocol import ModuleState
from robot_change.service.core import ServiceOptions
from robot_change.service.daemon import EXIT_STALLED, STALL_GRACE_S

BOUND = 2.0  # WATCHDOG_USEC=4 s: half of it, the floor of the stall bound


@pytest.mark.parametrize("where", ["detector", "check", "capture", "camera"])
def test_a_hang_is_a_fault_a_pause_no_more_watchdog_and_an_exit(tmp_path: Path,
                                                                where: str) -> None:
    with Daemon(tmp_path, hang=where) as d:
        d.wait_for("READY=1")
        if where in ("detector", "camera"):
            thread, result = d.base_in_thread(WATCH_SETUP + """
                expect FAULT code=STALLED 15
                expect PAUSE cause=INTERNAL_ERROR 3
                expect HEARTBEAT state=FAULT fault=1 2
            """)
            d.wait_for("WATCH office:")
            time.sleep(0.5)
            d.arm()
        else:
            d.arm()
            first = "" if where == "capture" else "capture office\nexpect CAPTURED 10\n"
            verb = "capture" if where == "capture" else "check"
            thread, result = d.base_in_thread(first + f"""
                {verb} office
                expect FAULT code=STALLED 15
                expect-none PAUSE 0.3
                expect HEARTBEAT state=FAULT fault=1 2
            """)
        entered = d.wait_entered()
        code = d.proc.wait(20)
        ended = time.monotonic()
        thread.join(20)
        assert result == [0], d.transcript.getvalue()[-3000:]
        assert code == EXIT_STALLED, d.log()
        # fed before the hang, never after the stall was found; a CHECK or a capture has the
        # command allowance on top of the bound
        bound = BOUND + (ServiceOptions().command_allowance_s if where in ("check", "capture")
                         else 0.0)
        assert d.pings(after=d.started), d.notes.lines
        late = d.pings(after=entered + bound + 1.0)
        assert not late, (entered, late)
        # the camera's bound is its read timeout (1 s) + 2 s; the watch's the interval + bound
        limit = (3.0 if where == "camera" else bound) + 0.5 + STALL_GRACE_S + 1.5
        assert ended - entered < limit, ended - entered
    text = d.log()
    assert "STALLED" in text and "not feeding the watchdog" in text
    assert "Traceback" not in text, text


def _sigterm_in(d: Daemon) -> None:
    code, seconds = d.terminate()
    assert code == 0, d.log()
    assert seconds <= 2.0, (seconds, d.log()[-2000:])
    time.sleep(0.1)
    assert "STOPPING=1" in d.notes.lines and not d.ready_after_stopping(), d.notes.lines


def test_sigterm_when_idle_and_when_watching(tmp_path: Path) -> None:
    for state in ("idle", "watching"):
        (tmp_path / state).mkdir()
        with Daemon(tmp_path / state) as d:
            d.wait_for("READY=1")
            if state == "watching":
                assert d.base(WATCH_SETUP + "wait 0.5") == 0, d.transcript.getvalue()[-3000:]
            _sigterm_in(d)


@pytest.mark.parametrize("where", ["detector", "check"])
def test_sigterm_with_a_hung_kernel(tmp_path: Path, where: str) -> None:
    with Daemon(tmp_path, hang=where, watchdog_usec=60_000_000) as d:  # no stall meanwhile
        d.wait_for("READY=1")
        if where == "detector":
            thread, _result = d.base_in_thread(WATCH_SETUP + "wait 4")
            d.wait_for("WATCH office:")
            d.arm()
        else:
            d.arm()
            thread, _result = d.base_in_thread("capture office\nexpect CAPTURED 10\n"
                                               "check office\nwait 4")
        d.wait_entered()
        time.sleep(0.3)
        _sigterm_in(d)
    assert "still running" in d.log()  # abandoned, not waited for


def test_sigterm_during_a_cold_compile_and_no_ready_after_it(tmp_path: Path) -> None:
    cache = tmp_path / "numba-cold"
    with Daemon(tmp_path, env={"NUMBA_CACHE_DIR": str(cache)}) as d:
        d.wait_for("STATUS=compiling the numba kernels (or loading them from the cache)")
        time.sleep(2.0)  # well inside the compile (~20 s cold on 2 cores)
        assert "READY=1" not in d.notes.lines
        _sigterm_in(d)
        time.sleep(1.0)
        assert "READY=1" not in d.notes.lines


def test_a_cold_start_talks_while_it_compiles(tmp_path: Path) -> None:
    """A start on an empty numba cache (an update without its warm-up): while the kernels
    compile the link is up, heartbeats say BOOTING and come no more than the base's silence
    rule apart (docs/protocol.md 7.6: 400 ms; the compile runs in helper processes, not in
    the daemon's interpreter), STATUS answers BOOTING, and a CAPTURE_REFERENCE sent then is
    run once the daemon is READY."""
    with Daemon(tmp_path, env={"NUMBA_CACHE_DIR": str(tmp_path / "numba-cold")}) as d:
        d.wait_for("STATUS=compiling the numba kernels (or loading them from the cache)")
        assert d.base("expect HEARTBEAT state=BOOTING 5\nstatus\n"
                      "expect STATUS state=BOOTING 3\ncapture office\n"
                      "expect CAPTURED station=office 150\nexpect HEARTBEAT state=IDLE 3") == 0
        ready = d.wait_for("READY=1", 5)
        booting = [e.t for e in d.sims[0].log
                   if e.name == "HEARTBEAT" and e.obj.state == ModuleState.BOOTING]
        assert ready - booting[0] > 5.0, "the compile was over before the base came"
        assert max(np.diff(booting)) < 0.4, "the compile held up the heartbeats"
        assert d.first("CAPTURED") > ready


def test_a_warm_up_past_its_deadline_is_a_stall_told_to_the_base(tmp_path: Path) -> None:
    """A warm-up that hangs (a compile stuck, or a computer far slower than planned) is no
    silent BOOTING until systemd's start timeout: at ``[service] warmup_timeout_s`` the base
    gets FAULT STALLED and heartbeats of state FAULT, and the daemon exits 70, never READY."""
    (tmp_path / "hang.arm").touch()  # armed from the start: the first warm-up call hangs
    with Daemon(tmp_path, hang="warmup", config="[service]\nwarmup_timeout_s = 10\n") as d:
        assert d.base("expect HEARTBEAT state=BOOTING 5\n"
                      "expect FAULT code=STALLED 15\n"
                      "expect HEARTBEAT state=FAULT fault=1 2") == 0, \
            d.transcript.getvalue()[-3000:]
        code = d.proc.wait(10)
        stalled = d.first("FAULT")
        assert code == EXIT_STALLED, d.log()
        assert 10.0 <= stalled - d.started < 14.0, stalled - d.started
        assert "READY=1" not in d.notes.lines and d.notes.lines, d.notes.lines
        assert any(line.startswith("EXTEND_TIMEOUT_USEC=70") for line in d.notes.lines)
    text = d.log()
    assert "warmup_timeout_s" in text and "Traceback" not in text, text


def test_a_base_that_stops_reading_is_no_stall(tmp_path: Path) -> None:
    """Nobody reads the line (a base that stopped reading: its buffer is full): the link
    drops what does not fit instead of waiting for room, so the daemon neither stalls nor
    exits, and a base that reads again is answered (it waited for ever, and exited 70)."""
    with Daemon(tmp_path) as d:
        d.wait_for("READY=1", 60)
        os.set_blocking(d.slave, False)
        try:
            while True:  # the module -> base direction, filled up
                os.write(d.slave, b"\x01" * 4096)
        except BlockingIOError:
            pass
        time.sleep(3 * BOUND)
        assert d.proc.poll() is None and "STALLED" not in d.log(), d.log()
        assert "takes no bytes" in d.log()
        assert d.base("status\nexpect STATUS state=IDLE 5") == 0


# --------------------------------------------------------------------------- one validation


BAD = {
    "novelty_quantile_5": ("[change]\nnovelty_quantile = 5.0\n", "novelty_quantile=5.0"),
    "novelty_quantile_neg": ("[change]\nnovelty_quantile = -1\n", "novelty_quantile=-1"),
    "posterior_threshold_7": ("[change]\nposterior_threshold = 7\n", "posterior_threshold=7"),
    "unknown_change_key": ("[change]\nnovelty_quantle = 0.02\n",
                           "did you mean change.novelty_quantile"),
    "state_dir_a_file": (None, "is not a folder"),
    "watch_m_over_n": ("[watch]\nwatch_m = 4\nwatch_n = 3\n", "must be <= watch.watch_n"),
    "not_toml": ("[camera\n", "invalid TOML"),
}


def _write_bad(tmp: Path, key: str) -> Path:
    text, _ = BAD[key]
    path = tmp / f"{key}.toml"
    if text is None:
        (tmp / "a-file").write_text("x")
        text = f"[store]\nstate_dir = {str(tmp / 'a-file')!r}\n"
    path.write_text("[serial]\nport = 'loop://'\n" + text)
    return path


@pytest.mark.parametrize("key", sorted(BAD))
def test_check_config_and_run_refuse_the_same_files_the_same_way(tmp_path: Path,
                                                                 key: str) -> None:
    path = _write_bad(tmp_path, key)
    out = {}
    for command in (["check-config", str(path)], ["run", "--config", str(path)]):
        done = subprocess.run([sys.executable, "-m", "robot_change.cli", *command], cwd=REPO,
                              capture_output=True, text=True, timeout=60)
        assert done.returncode == 78, (command, done.stdout, done.stderr)
        assert BAD[key][1] in done.stderr and "Traceback" not in done.stderr, done.stderr
        out[command[0]] = done.stderr.split("configuration error: ", 1)[1]
    assert out["check-config"] == out["run"]


def test_a_refused_reload_keeps_the_old_configuration_and_says_so(tmp_path: Path) -> None:
    import signal

    with Daemon(tmp_path) as d:
        d.wait_for("READY=1")
        assert d.base("capture office\nexpect CAPTURED 10") == 0
        d.write_config("[change]\nnovelty_quantile = 5.0\n")
        d.proc.send_signal(signal.SIGHUP)
        d.wait_for("the new configuration is refused, the old one stays")
        end = time.monotonic() + 5  # the STATUS follows the log line
        while time.monotonic() < end and not any("refused" in line for line in d.notes.lines):
            time.sleep(0.02)
        statuses = [line for line in d.notes.lines if line.startswith("STATUS=")]
        assert any("refused, the old one stays" in s for s in statuses), statuses
        assert not any(s == "STATUS=configuration reloaded" for s in statuses), statuses
        # the old configuration goes on working: no INTERNAL_ERROR
        assert d.base("check office\nexpect CLEAR 10") == 0, d.transcript.getvalue()[-3000:]
        # files cut short at a line: valid TOML, their last section ([store]) or its last key
        # gone (issue 44)
        d.write_config("[watch]\nwatch_m = 2\n")
        d.proc.send_signal(signal.SIGHUP)
        d.wait_for("STATUS=configuration reloaded")
        whole = d.config.read_text()
        d.config.write_text(whole[: whole.index("[store]")])
        d.proc.send_signal(signal.SIGHUP)
        d.wait_for("does not set store.state_dir, watch.watch_m, which the running")
        d.config.write_text(whole[: whole.index("watch_m")])
        d.proc.send_signal(signal.SIGHUP)
        d.wait_for("does not set watch.watch_m, which the running")
        assert d.base("check office\nexpect CLEAR 10") == 0, d.transcript.getvalue()[-3000:]
        _sigterm_in(d)


def test_a_configuration_the_reference_was_not_captured_with_is_said_once(tmp_path: Path
                                                                          ) -> None:
    """Another camera's profile or other cloud parameters were taken in silence: the check
    went on with the reference's, and nothing said the configuration was not in force."""
    import signal

    with Daemon(tmp_path) as d:
        d.wait_for("READY=1")
        assert d.base("capture office\nexpect CAPTURED 10") == 0, d.transcript.getvalue()[-3000:]
        text = d.config.read_text().replace("[camera]\n", '[camera]\nprofile = "realsense_d435"\n')
        d.config.write_text(text + "[cloud]\nleaf_m = 0.02\n")
        d.proc.send_signal(signal.SIGHUP)
        d.wait_for("STATUS=configuration reloaded")
        assert d.base("check office\nexpect CLEAR 10\ncheck office\nexpect CLEAR 10") == 0
        said = [line for line in d.log().splitlines() if "its reference was captured with" in line]
        assert len(said) == 1, said  # once, not at every check
        assert "noise profile kinect_v1, the configuration says realsense_d435" in said[0]
        assert "leaf_m 0.03 vs 0.02" in said[0] and "capture the station again" in said[0]
        # a check needs not the configured profile: a profile file gone after the reload is
        # said, and the check answers
        from robot_change.noise.profile import builtin_profile
        profile = builtin_profile("xtion").save(tmp_path / "camera.json")
        d.config.write_text(text.replace('[camera]\n', f'[camera]\nprofile_file = "{profile}"\n')
                            + "[cloud]\nleaf_m = 0.02\n")
        d.proc.send_signal(signal.SIGHUP)
        end = time.monotonic() + 20  # the second reload's line
        while d.log().count("configuration reloaded") < 2:
            assert time.monotonic() < end, d.log()[-3000:]
            time.sleep(0.05)
        profile.unlink()
        assert d.base("check office\nexpect CLEAR 10") == 0, d.transcript.getvalue()[-3000:]
        assert "the configuration says an unreadable file" in d.log(), d.log()[-3000:]
        _sigterm_in(d)


def test_a_burst_of_sighups_is_taken_and_sigterm_still_stops_the_daemon(tmp_path: Path) -> None:
    """Each handler set an Event, whose lock the main thread may hold when a signal comes: a
    burst of SIGHUPs hung the daemon for good (2 of 3 runs), SIGTERM ignored, no stall
    detected; a longer one ended it by a traceback and SIGHUP's default action."""
    import signal

    with Daemon(tmp_path) as d:
        d.wait_for("READY=1")
        for i in range(2000):
            d.proc.send_signal(signal.SIGHUP)
            if i % 50 == 0:
                time.sleep(0.01)
        d.write_config("[watch]\nwatch_m = 2\n")  # a reload after the burst is still taken
        d.proc.send_signal(signal.SIGHUP)
        d.wait_for("STATUS=configuration reloaded")
        assert d.proc.poll() is None and "Traceback" not in d.log(), d.log()[-3000:]
        assert d.base("capture office\nexpect CAPTURED 10") == 0, d.transcript.getvalue()[-3000:]
        _sigterm_in(d)


def test_a_restart_leaves_no_temp_file_anywhere_the_service_writes(tmp_path: Path) -> None:
    """Issue 44: the daemon killed with SIGKILL while it writes a check's files, and temp files
    as killed writes leave them in every folder the service writes (references and their
    quarantine, the last checks, the check views, the fleet's spool): once it has started
    again, none is left, and the reference is whole."""
    state = tmp_path / "state"
    # nothing listens at the broker: messages spool; no views of the checks (a view is written
    # after the answer, on a thread of its own: its temp file may be there at any moment)
    fleet = '[fleet]\nbroker = "mqtt://127.0.0.1:9"\n[viz]\nkeep_checks = 0\n'
    with Daemon(tmp_path / "first", state_dir=state, config=fleet) as d:
        d.wait_for("READY=1")
        assert d.base("capture office\nexpect CAPTURED station=office 20") == 0, d.log()
        d.base_in_thread("check office\nexpect CLEAR 20\n" * 40)
        reports = state / "reports"
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and not list(reports.glob(".*.tmp")):
            pass
        d.proc.kill()
        d.proc.wait(10)
    folders = [state / "references", state / "references" / "quarantine", reports,
               reports / "checks", state / "fleet-spool"]
    for folder in folders:
        folder.mkdir(parents=True, exist_ok=True)
        (folder / ".office.last-check.npz.k3j9x.tmp").write_bytes(b"half a file")
    killed = {p.relative_to(state) for p in state.rglob("*.tmp")}
    with Daemon(tmp_path / "second", state_dir=state, config=fleet) as d:
        d.wait_for("READY=1")
        assert d.base("check office\nexpect CLEAR station=office 20") == 0, d.log()
        left = {p.relative_to(state) for p in state.rglob("*.tmp")}
        assert not left & killed, sorted(map(str, left & killed))
        # the running daemon's own writes (the spool's messages: nothing listens at the
        # broker) are temp files for a moment, then renamed
        deadline = time.monotonic() + 10
        while left and time.monotonic() < deadline:
            time.sleep(0.05)
            left &= {p.relative_to(state) for p in state.rglob("*.tmp")}
        assert not left, sorted(map(str, left))
