"""The fleet over MQTT: many modules on one broker, and whether a broker in trouble delays the
robot.

    flock /tmp/robot_change_bench.lock .venv/bin/python bench/bench_fleet.py \
        [--modules 100] [--seconds 60] [--processes 4] [--rounds 30] [--json OUT]

1. ``fleet``: one local Mosquitto (tests/fleet_rig.py: Debian's, on a free loopback port),
   ``--modules`` simulated modules -- the real robot_change.fleet.publisher.Publisher, each
   with its own on-disk spool, spread over ``--processes`` processes -- each publishing one
   check report per second (a real report's size, ~2.5 kB) for ``--seconds``; one subscriber
   (QoS 1) takes them all.  End-to-end latency: from ``report()`` (the daemon's call) to the
   subscriber's callback, through the writer thread, the spool's fsync, the broker;
   p50 / p99 / max, and loss (reports published and never received, by report id).
2. ``pause``: CHECK -> PAUSE latency at the simulated base (tests/daemon_rig.py: the real
   daemon, an image folder as the camera, a pty pair) for three daemons at once: no fleet, a
   dead broker (connection refused), a broker that accepts TCP and never answers; rounds
   interleaved (one check on each in turn, the order rotated), ``--rounds`` per daemon.

A benchmark, never a test; docs/benchmarks.md ("Fleet") reports its output.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import signal
import socket
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT))

import paho.mqtt.client as mqtt  # noqa: E402
from fleet_rig import Broker, free_port  # noqa: E402

from robot_change.fleet.connection import BrokerSettings  # noqa: E402
from robot_change.fleet.publisher import Publisher  # noqa: E402
from robot_change.fleet.spool import Spool  # noqa: E402


def _report(n: int) -> dict:
    """A check report the size of a real one (~2.5 kB of JSON: registration, two regions)."""
    region = {"kind": "appeared", "centroid_m": [0.12, 0.05, 1.9], "extent_m": [0.3, 0.25, 0.3],
              "bbox_min_m": [-0.03, -0.07, 1.75], "bbox_max_m": [0.27, 0.18, 2.05],
              "n_points": 812, "n_pixels": 5120, "components": [3, 4],
              "base": {"centroid_m": [2.1, -0.12, 0.31], "extent_m": [0.3, 0.3, 0.25],
                       "bbox_min_m": [1.95, -0.27, 0.18], "bbox_max_m": [2.25, 0.03, 0.43]}}
    return {"outcome": "changed", "changed": True, "method": "novelty", "station": "office",
            "registration": {"T_ref_from_cur": [[1.0, 0.0, 0.0, 0.01]] * 4, "fitness": 0.97,
                             "rmse_m": 0.004, "translation_m": [0.01, 0.0, 0.002],
                             "rotation_deg": 0.3, "weak_directions": [], "iterations": 14},
            "unobserved_fraction": 0.03, "not_at_station_reason": "",
            "mount": {"xyz_m": [0.2, 0.0, 0.45], "rpy_deg": [0.0, 10.0, 0.0]},
            "offset_base": {"translation_m": [0.01, 0.0, 0.0], "rpy_deg": [0.0, 0.0, 0.3],
                            "weak_directions": []},
            "regions": [region, dict(region, kind="disappeared")], "n": n,
            "n_appeared_points": 812, "n_disappeared_points": 640, "k_reference": 16,
            "k_current": 16, "k_appeared_mixture": 2, "k_disappeared_mixture": 1,
            "greedy_appeared": None, "greedy_disappeared": None,
            "timings_ms": {f"stage_{i}": 1.234 for i in range(12)}}


def _modules(url: str, first: int, count: int, total: int, seconds: float, folder: str,
             start_at: float, out: multiprocessing.Queue) -> None:
    """``count`` simulated modules in this process, one report per second each."""
    publishers = []
    for i in range(first, first + count):
        spool = Spool(Path(folder) / f"m{i:03d}", 64 << 20)
        publisher = Publisher(BrokerSettings(url), f"m{i:03d}", spool,
                              status=lambda: {"state": "idle", "armed": True})
        publisher.start()
        publishers.append(publisher)
    sent = 0
    for tick in range(int(seconds)):
        for k, publisher in enumerate(publishers):
            due = start_at + tick + (first + k) / total  # spread over the second
            delay = due - time.time()
            if delay > 0:
                time.sleep(delay)
            publisher.report("office", _report(tick))
            sent += 1
    deadline = time.time() + 60
    while time.time() < deadline and any(len(p.spool) for p in publishers):
        time.sleep(0.1)
    for publisher in publishers:
        publisher.close(1.0)
    out.put({"sent": sent, "left_in_spools": sum(len(p.spool) for p in publishers),
             "queue_dropped": sum(p.queue_dropped for p in publishers)})


def bench_fleet(modules: int, seconds: float, processes: int) -> dict:
    with tempfile.TemporaryDirectory() as tmp, Broker(Path(tmp) / "broker") as broker:
        latencies: list[float] = []
        seen: set[tuple[str, str]] = set()
        duplicates = [0]
        lock = threading.Lock()

        def on_message(_c, _u, m) -> None:
            now = time.time()
            message = json.loads(m.payload)
            with lock:
                key = (message["robot"], message["report_id"])
                if key in seen:
                    duplicates[0] += 1
                    return
                seen.add(key)
                latencies.append(now - message["time_unix"])

        subscriber = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2)
        subscriber.on_message = on_message
        subscriber.connect("127.0.0.1", broker.port)
        subscriber.subscribe("robot-change/+/checks/#", 1)
        subscriber.loop_start()
        time.sleep(0.5)
        load_before = os.getloadavg()
        out: multiprocessing.Queue = multiprocessing.Queue()
        share = [modules // processes + (1 if i < modules % processes else 0)
                 for i in range(processes)]
        start_at = time.time() + 3.0  # every module connected by then
        procs, first = [], 0
        for count in share:
            proc = multiprocessing.Process(target=_modules, args=(
                broker.url, first, count, modules, seconds, tmp, start_at, out))
            proc.start()
            procs.append(proc)
            first += count
        results = [out.get(timeout=seconds + 120) for _ in procs]
        for proc in procs:
            proc.join(30)
        load_after = os.getloadavg()
        time.sleep(1.0)
        subscriber.loop_stop()
        subscriber.disconnect()
    sent = sum(r["sent"] for r in results)
    ordered = sorted(latencies)

    def pct(q: float) -> float:
        return round(1e3 * ordered[min(len(ordered) - 1, int(q * len(ordered)))], 2)

    return {"modules": modules, "seconds": seconds, "processes": processes,
            "published": sent, "received": len(seen), "lost": sent - len(seen),
            "duplicates": duplicates[0],
            "left_in_spools": sum(r["left_in_spools"] for r in results),
            "queue_dropped": sum(r["queue_dropped"] for r in results),
            "latency_ms": {"p50": pct(0.5), "p90": pct(0.9), "p99": pct(0.99),
                           "max": round(1e3 * ordered[-1], 2)},
            "loadavg_before": load_before, "loadavg_after": load_after}


# ---------------------------------------------------------------------------------------------
# CHECK -> PAUSE with the broker in trouble


def _silent_broker() -> tuple[socket.socket, int]:
    """A TCP listener that never accepts: connections complete, CONNACK never comes."""
    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    sock.listen(64)
    return sock, sock.getsockname()[1]


def bench_pause(rounds: int) -> dict:
    from daemon_rig import Daemon

    from hw.serial_port import FdPort
    from robot_change.link.session import LinkState
    from robot_change.tools.basesim import BaseSim

    silent, silent_port = _silent_broker()
    conditions = {
        "no fleet": "",
        "broker dead (refused)": f'[fleet]\nbroker = "mqtt://127.0.0.1:{free_port()}"\n'
                                 'robot_id = "dead"\n',
        "broker silent (no CONNACK)": f'[fleet]\nbroker = "mqtt://127.0.0.1:{silent_port}"\n'
                                      'robot_id = "silent"\n',
    }
    times: dict[str, list[float]] = {name: [] for name in conditions}
    with tempfile.TemporaryDirectory() as tmp:
        daemons = {name: Daemon(Path(tmp) / f"d{i}", config=text)
                   for i, (name, text) in enumerate(conditions.items())}
        try:
            sims = {}
            for name, d in daemons.items():
                d.wait_for("READY=1")
                sims[name] = BaseSim(FdPort(d.master), out=open(os.devnull, "w"))

            def pump_all(until, timeout: float) -> bool:
                end = time.monotonic() + timeout
                while time.monotonic() < end:
                    for sim in sims.values():
                        sim.pump(0.001)  # (a step of each link, waiting at most 1 ms)
                    if until():
                        return True
                return False

            def ask(name: str, line: str, answer: str, timeout: float = 10.0) -> None:
                sim = sims[name]
                start = len(sim.log)
                sim.command(line)
                assert pump_all(lambda: any(e.name == answer for e in sim.log[start:]),
                                timeout), f"{name}: {line}: no {answer}\n{daemons[name].log()}"

            assert pump_all(lambda: all(s.link.state == LinkState.UP for s in sims.values()),
                            10), {n: (s.link.state, daemons[n].log()[-600:])
                                  for n, s in sims.items()}
            for name, d in daemons.items():
                ask(name, "capture office", "CAPTURED")
                ask(name, "set fuse_frames 1", "PARAM_VALUE")
                d.write_config(epoch="current")
                d.proc.send_signal(signal.SIGHUP)
                assert pump_all(lambda d=d: "reopening the camera" in d.log(), 10)
            pump_all(lambda: False, 1.0)
            names = list(conditions)
            for r in range(rounds):
                order = names[r % 3:] + names[:r % 3]
                for name in order:
                    sim = sims[name]
                    start = len(sim.log)
                    t0 = sim.clock()
                    sim.command("check office")

                    def paused(sim=sim, start=start) -> bool:
                        return any(e.name == "PAUSE" for e in sim.log[start:])

                    assert pump_all(paused, 10), f"{name}: no PAUSE"
                    pause = next(e for e in sim.log[start:] if e.name == "PAUSE")
                    times[name].append(pause.t - t0)
                    pump_all(lambda sim=sim, start=start:
                             any(e.name == "REPORT" for e in sim.log[start:]), 5)
                    ask(name, "resume", "HEARTBEAT")
                    pump_all(lambda: False, 0.2)
            logs = {name: d.log() for name, d in daemons.items()}
        finally:
            for d in daemons.values():
                d.__exit__(None, None, None)
            silent.close()
    out = {}
    for name, values in times.items():
        ordered = sorted(values)
        out[name] = {"n": len(values), "median_ms": round(1e3 * statistics.median(values), 1),
                     "p90_ms": round(1e3 * ordered[int(0.9 * (len(ordered) - 1))], 1),
                     "max_ms": round(1e3 * ordered[-1], 1)}
    out["fleet log lines"] = {name: sum("fleet:" in line for line in text.splitlines())
                              for name, text in logs.items()}
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--modules", type=int, default=100)
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--processes", type=int, default=4)
    parser.add_argument("--rounds", type=int, default=30)
    parser.add_argument("--only", choices=("fleet", "pause"))
    parser.add_argument("--json", help="also write the results to this file")
    args = parser.parse_args()
    result: dict = {"machine": {"cpus": os.cpu_count(), "loadavg_at_start": os.getloadavg()}}
    if args.only in (None, "fleet"):
        result["fleet"] = bench_fleet(args.modules, args.seconds, args.processes)
        print(json.dumps({"fleet": result["fleet"]}), flush=True)
    if args.only in (None, "pause"):
        result["pause"] = bench_pause(args.rounds)
        print(json.dumps({"pause": result["pause"]}), flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
