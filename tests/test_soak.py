"""Issue 7's soak, the CI version: ``robot-change run`` as a real subprocess WATCHING the looped
office_box_added/reference.oni at 30 fps for 60 s, the simulated base on a pty pair, then
SIGTERM.  The figures come from bench/bench_service.py (``soak_daemon``, the same code as
``bench_service.py --only soak-daemon --soak-seconds 600``, the full 10-minute soak):

* RSS of the daemon (and of its OpenNI2 reader child) from the end of a 20 s warm-up to the
  end grows by <= 10 %: a gross leak (a frame kept per frame: 18 MB/s; 0.35 MB kept per watch
  check) shows; the slow kind is the hour's soak's to find (bench/bench_service.py, its slope).
  The heap keeps a new peak of a check's allocations: one step of ~11 MB (4.3 %) at a time no
  one chooses, at 6, 10, 21 and 43 s into runs with the thread count unchanged, flat after it;
  at 5 % a step after the warm-up failed the test (5.44 %, 2026-12-07);
* no stall: no gap between the module's heartbeats (every 0.1 s) above 1 s;
* every frame accounted for: received == processed + dropped + queued, and received == the
  frames the OpenNI2 source itself delivered (counts the daemon writes when it stops);
* the daemon exits 0 on SIGTERM.

About 70 s (READY with a warm numba cache, a capture, 60 s of watching, the stop).
"""

from __future__ import annotations

import json
import time

from bench.bench_service import soak_daemon

SECONDS = 60.0
WARMUP = 20.0
MAX_RSS_GROWTH_PCT = 10.0
MAX_HEARTBEAT_GAP_S = 1.0


def test_daemon_soak_60s_watching_at_30fps() -> None:
    started = time.monotonic()
    r = soak_daemon(SECONDS, warmup=WARMUP)
    took = time.monotonic() - started
    log = r.pop("daemon_log_tail")
    figures = json.dumps(r)
    where = f"\nall figures: {figures}\ndaemon log (tail):\n{log}"

    assert r["exit_status"] == 0, f"the daemon exited {r['exit_status']} on SIGTERM{where}"
    assert r["rss_growth_pct"] <= MAX_RSS_GROWTH_PCT, (
        f"daemon RSS grew {r['rss_growth_pct']} % over {SECONDS - WARMUP:.0f} s "
        f"({r['rss_start_mb']} MB after the {WARMUP:.0f} s warm-up -> {r['rss_end_mb']} MB at "
        f"the end; limit {MAX_RSS_GROWTH_PCT} %){where}")
    assert r["reader_rss_growth_pct"] <= MAX_RSS_GROWTH_PCT, (
        f"the OpenNI2 reader child's RSS grew {r['reader_rss_growth_pct']} % "
        f"({r['reader_rss_start_mb']} MB -> {r['reader_rss_end_mb']} MB; limit "
        f"{MAX_RSS_GROWTH_PCT} %){where}")
    assert r["longest_heartbeat_gap_s"] <= MAX_HEARTBEAT_GAP_S, (
        f"stall: the longest gap between heartbeats at the base was "
        f"{r['longest_heartbeat_gap_s']} s (limit {MAX_HEARTBEAT_GAP_S} s){where}")
    f = r["frames"]
    assert f["received"] == f["processed"] + f["dropped"] + f["queued"], (
        f"frames not accounted for: received {f['received']} != processed {f['processed']} + "
        f"dropped {f['dropped']} + queued {f['queued']}{where}")
    assert f["received"] == r["source_delivered"], (
        f"the daemon received {f['received']} frames but the source delivered "
        f"{r['source_delivered']}{where}")
    # 30 fps for the 60 s of watching (and the capture before): frames really flowed
    assert f["received"] >= 0.9 * 30 * SECONDS, (
        f"only {f['received']} frames received in {SECONDS:.0f} s at 30 fps{where}")
    assert r["camera_losses"] == 0 and set(r["heartbeat_states"]) == {"WATCHING"}, (
        f"the watch did not run throughout: camera losses {r['camera_losses']}, heartbeat "
        f"states {r['heartbeat_states']}{where}")
    print(f"soak of {SECONDS:.0f} s in {took:.0f} s: {figures}")  # shown with -rP / -s
