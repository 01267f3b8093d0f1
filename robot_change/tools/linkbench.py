"""``robot-change link-bench``: PAUSE round trips, reports, STATUS and floods through a noisy,
baud-paced serial line.

Two pseudo-terminal pairs joined by a relay: module Link <-> pyserial port <-> pty <-> relay <->
pty <-> pyserial port <-> base Link.  The relay lets bytes through at the line's pace (baud / 10
bytes per second, 8N1) and corrupts each byte with probability ``corrupt`` (XOR with a random
non-zero value: bit flips, false delimiters, lost delimiters).  The links connect over a clean
line; then the noise is switched on.  ``noise="mixed"`` (the default) corrupts a byte in one of
three ways in equal shares: a bit flip (XOR with a random non-zero value), a drop, or an inserted
random byte before it; ``noise="flip"`` only flips.

Modes (``mode``):

- ``pause``: the module sends ``count`` PAUSEs, one at a time.
- ``report``: ``count`` CHECK answers, one at a time: PAUSE, then (version >= 2) CHECK_RESULT and
  the CHANGE_REPORT parts of ``regions`` regions; the base sends RESUME when the report is whole
  (or after ``report_timeout``).  A report counts as complete when the base has joined it
  within ``report_timeout`` (5 s) of the PAUSE being sent.
- ``check``: ``count`` CHECKs from the base, one at a time; the module answers each the way the
  service does (PAUSE, CHECK_RESULT, the report), then the base sends RESUME.  Counted: CHECKs
  the module received, answers whose PAUSE and whole report the base had within
  ``report_timeout`` of sending the CHECK, and the base's link faults: both directions.
- ``restart``: ``count`` times the module restarts (a new Link, a new boot id; what the old one
  had on the line still arrives) and the base must see the new boot: the time from the new
  module's start to the base receiving its HELLO, and to both ends speaking ``proto`` again.
- ``idle``: ``count`` seconds of heartbeats alone (the base parked, nothing to say): counted are
  the link faults each end declares, which must be none while both ends are alive.
- ``status``: ``count`` STATUS_QUERY -> STATUS round trips from the base, one at a time.
- ``flood``: the base queues ``count`` STATUS_QUERYs at once; the module answers each the way
  the service does (coalesced: one STATUS in flight, one waiting); counted: queries
  acknowledged, refused, STATUS received, answers dropped.

``proto`` (the newest by default) is the highest version both ends offer: 2 measures the
whole-frame transport of versions 1 and 2, 4 the module's PARTs with the base's whole frames,
5 PARTs both ways.

A round trip counts as delivered when the base received the PAUSE and the module received its
ACK; its latency is from ``send()`` to that ACK.  Everything runs in one thread (select), so the
figures are the protocol's, not the scheduler's.
"""

from __future__ import annotations

import os
import random
import select
import statistics
import sys
import time
import tty
from collections import deque
from typing import Any, TextIO

from hw.serial_port import open_port
from robot_change import json_text
from robot_change.errors import InputError, LinkError
from robot_change.link.protocol import (
    VERSION,
    BaseHeartbeat,
    ChangeReport,
    Check,
    CheckOutcome,
    CheckResult,
    Heartbeat,
    Hello,
    ModuleState,
    Motion,
    Pause,
    PauseCause,
    Region,
    RegionKind,
    ReportAssembler,
    Resume,
    Role,
    Status,
    StatusQuery,
    split_change_report,
)
from robot_change.link.session import (
    Delivered,
    Link,
    LinkConfig,
    LinkState,
    Received,
    SendFailed,
    StateChanged,
)

#: ``restart`` mode: how long a restarting module is silent (stopped, not yet started again).
RESTART_SILENCE = 0.3
MODES = ("pause", "report", "check", "restart", "idle", "status", "flood")
NOISES = ("mixed", "flip")


class _Direction:
    """One direction of the relay: paced, corrupting, writing to a pty master."""

    def __init__(self, fd_out: int, byte_rate: float, rng: random.Random, noise: str) -> None:
        self.fd_out = fd_out
        self.byte_rate = byte_rate
        self.rng = rng
        self.noise = noise
        self.corrupt = 0.0
        self.queue: deque[tuple[float, int]] = deque()
        self.free_at = 0.0
        self.bytes = 0
        self.corrupted = 0

    def push(self, data: bytes, now: float) -> None:
        out = bytearray()
        rng = self.rng
        for byte in data:
            if self.corrupt and rng.random() < self.corrupt:
                self.corrupted += 1
                kind = 0 if self.noise == "flip" else rng.randrange(3)
                if kind == 0:
                    out.append(byte ^ rng.randrange(1, 256))
                elif kind == 2:
                    out += bytes((rng.randrange(256), byte))
                continue  # kind 1: dropped
            out.append(byte)
        start = max(self.free_at, now)
        for i, byte in enumerate(out):
            self.queue.append((start + (i + 1) / self.byte_rate, byte))
        self.free_at = start + len(out) / self.byte_rate
        self.bytes += len(data)

    def flush(self, now: float) -> None:
        out = bytearray()
        while self.queue and self.queue[0][0] <= now:
            out.append(self.queue.popleft()[1])
        if out:
            os.write(self.fd_out, bytes(out))

    def next_due(self) -> float:
        return self.queue[0][0] if self.queue else float("inf")


def _percentile(values: list[float], q: float) -> float | None:
    if not values:
        return None
    ordered = sorted(values)
    rank = max(0, min(len(ordered) - 1, int(round(q / 100 * len(ordered) + 0.5)) - 1))
    return ordered[rank]


def _ms(value: float | None) -> float | None:
    return None if value is None else round(value * 1000, 1)


def run_link_bench(corrupt: float = 0.1, count: int = 200, baud: int = 115200, json: bool = False,
                   *, seed: int | None = None, timeout: float = 2.0, gap: float = 0.02,
                   out: TextIO | None = None, mode: str = "pause", noise: str = "mixed",
                   proto: int = VERSION, regions: int = 3,
                   report_timeout: float = 5.0) -> dict[str, Any]:
    """Run the bench; print the result (one JSON object with ``json``) and return it as a dict.

    Keys of every mode: mode, proto, noise, sent, corrupt, baud, seconds, retransmissions,
    parts_sent (both ends), bad_frames, bytes, corrupted_bytes, link_faults (the module's),
    base_link_faults.  ``pause`` adds delivered, received_by_base, failed, p50_ms, p99_ms,
    max_ms (round trips), one_way_p50_ms, one_way_p99_ms; ``report``: pauses_received,
    reports_complete, report_p50_ms, report_p99_ms, report_max_ms, resumes_delivered;
    ``check``: reached, answered, answer_p50_ms, answer_p99_ms, answer_max_ms,
    resumes_delivered; ``restart``: seen, seen_p50_ms, seen_p99_ms, seen_max_ms, ready,
    ready_p50_ms, ready_p99_ms; ``idle``: (the faults only); ``status``: answered,
    status_p50_ms, status_p99_ms; ``flood``:
    acked, refused, status_received, answers_dropped.
    """
    if not 0 <= corrupt < 1:
        raise InputError(f"--corrupt {corrupt}: give a probability per byte, 0 <= p < 1")
    if not 1 <= count <= 1_000_000:
        raise InputError(f"--count {count}: give 1..1000000 round trips")
    if not 300 <= baud <= 4_000_000:
        raise InputError(f"--baud {baud}: give 300..4000000")
    if mode not in MODES:
        raise InputError(f"--mode {mode}: give one of {', '.join(MODES)}")
    if noise not in NOISES:
        raise InputError(f"--noise {noise}: give one of {', '.join(NOISES)}")
    if not 1 <= proto <= VERSION:
        raise InputError(f"--proto {proto}: give 1..{VERSION}")
    if not 0 <= regions <= 2805:
        raise InputError(f"--regions {regions}: give 0..2805")
    out = out or sys.stdout
    rng = random.Random(seed)
    fds: list[int] = []
    ports: list[Any] = []
    try:
        ma, sa = os.openpty()
        mb, sb = os.openpty()
        fds += [ma, mb]
        for slave in (sa, sb):
            tty.setraw(slave)
        port_m = open_port(os.ttyname(sa), baudrate=baud, timeout=0)
        port_b = open_port(os.ttyname(sb), baudrate=baud, timeout=0)
        ports += [port_m, port_b]
        os.close(sa)
        os.close(sb)
        for fd in (ma, mb):
            os.set_blocking(fd, False)
        bench = _Bench(port_m, port_b, ma, mb, _Direction(mb, baud / 10, rng, noise),
                       _Direction(ma, baud / 10, rng, noise), LinkConfig.for_baud(baud), proto,
                       mode == "flood" and count)
        result = {"mode": mode, "proto": proto, "noise": noise}
        result.update(getattr(bench, f"run_{mode}")(corrupt, count, timeout, gap, regions,
                                                    report_timeout))
        result.update(bench.totals(corrupt, baud))
    finally:
        for port in ports:
            port.close()
        for fd in fds:
            os.close(fd)
    if json:
        print(json_text.dumps(result), file=out)
    else:
        print(_summary(result), file=out)
    return result


def _summary(r: dict[str, Any]) -> str:
    line = (f"{r['mode']} at {r['baud']} baud, {r['corrupt']:.0%} of bytes corrupted "
            f"({r['noise']}), protocol {r['proto']}: sent {r['sent']}, ")
    pct = (lambda n: f"{n} ({100.0 * n / r['sent']:.1f}%)") if r["sent"] else str
    if r["mode"] == "pause":
        line += (f"delivered {pct(r['delivered'])}, p50 {r['p50_ms']} ms, p99 {r['p99_ms']} ms, "
                 f"max {r['max_ms']} ms")
    elif r["mode"] == "report":
        line += (f"PAUSE received {pct(r['pauses_received'])}, reports complete within "
                 f"{r['report_timeout_s']:g} s {pct(r['reports_complete'])}, p50 "
                 f"{r['report_p50_ms']} ms, p99 {r['report_p99_ms']} ms; RESUME delivered "
                 f"{pct(r['resumes_delivered'])}")
    elif r["mode"] == "check":
        line += (f"reached the module {pct(r['reached'])}, PAUSE and the whole report within "
                 f"{r['report_timeout_s']:g} s {pct(r['answered'])}, p50 {r['answer_p50_ms']} ms, "
                 f"p99 {r['answer_p99_ms']} ms; RESUME delivered {pct(r['resumes_delivered'])}")
    elif r["mode"] == "restart":
        line += (f"new boot seen {pct(r['seen'])}, p50 {r['seen_p50_ms']} ms, p99 "
                 f"{r['seen_p99_ms']} ms, max {r['seen_max_ms']} ms; both ends at protocol "
                 f"{r['proto']} again p50 {r['ready_p50_ms']} ms, p99 {r['ready_p99_ms']} ms")
    elif r["mode"] == "idle":
        line += "seconds of heartbeats alone"
    elif r["mode"] == "status":
        line += (f"answered {pct(r['answered'])}, p50 {r['status_p50_ms']} ms, p99 "
                 f"{r['status_p99_ms']} ms")
    else:
        line += (f"acked {r['acked']}, refused {r['refused']}, failed {r['failed']}, STATUS "
                 f"received {r['status_received']}, answers dropped {r['answers_dropped']}")
    return line + (f"; {r['retransmissions']} retransmissions, {r['parts_sent']} PARTs, "
                   f"{r['bad_frames']} bad frames, link faults: module {r['link_faults']}, "
                   f"base {r['base_link_faults']}")


class _Bench:
    """The two links, the relay, and one loop that pumps them all (select, one thread)."""

    def __init__(self, port_m: Any, port_b: Any, ma: int, mb: int, to_base: _Direction,
                 to_module: _Direction, config: LinkConfig, proto: int, flood: int) -> None:
        base_config = config
        if flood:  # the base queues the whole flood at once
            from dataclasses import replace
            base_config = replace(config, max_queue=max(config.max_queue, flood))
        self.config, self.proto = config, proto
        self.module = self.new_module()
        self.base = Link(Role.BASE, config=base_config, proto_max=proto)
        self.base.set_heartbeat(BaseHeartbeat(Motion.PARKED))
        self.port_m, self.port_b, self.ma, self.mb = port_m, port_b, ma, mb
        self.to_base, self.to_module = to_base, to_module
        self.faults = self.base_faults = 0
        self.module_off = False
        self.start = time.monotonic()
        self.module_events: list[Any] = []
        self.base_events: list[Any] = []
        self.status_seq = 0

    def new_module(self) -> Link:
        """A module's link as one starts: a new boot id, version 1 until the base's HELLO."""
        module = Link(Role.MODULE, config=self.config, proto_max=self.proto)
        module.set_heartbeat(Heartbeat(ModuleState.WATCHING, paused=True, armed=True,
                                       fps_x10=300))
        return module

    def pump(self, max_wait: float = 0.01) -> float:
        """One turn: timers, writes, relay, reads.  Events pile up in *_events."""
        now = time.monotonic()
        links = ((self.module, self.port_m), (self.base, self.port_b))
        for link, port in links[self.module_off:]:
            link.poll(now)
            data = link.outgoing()
            if data:
                port.write(data)
        self.to_base.flush(now)
        self.to_module.flush(now)
        deadline = min(float("inf") if self.module_off else self.module.next_deadline(),
                       self.base.next_deadline(),
                       self.to_base.next_due(), self.to_module.next_due(), now + max_wait)
        fds = [self.port_m.fileno(), self.port_b.fileno(), self.ma, self.mb]
        readable, _, _ = select.select(fds, [], [], max(0.0, deadline - now))
        now = time.monotonic()
        for fd in readable:
            if fd == fds[0]:
                data = self.port_m.read(self.port_m.in_waiting or 1)
                if not self.module_off:  # a module between two lives hears nothing
                    self.module.receive(data, now)
            elif fd == fds[1]:
                self.base.receive(self.port_b.read(self.port_b.in_waiting or 1), now)
            else:
                try:
                    data = os.read(fd, 4096)
                except BlockingIOError:
                    continue
                (self.to_base if fd == self.ma else self.to_module).push(data, now)
        for event in self.module.events():
            if isinstance(event, StateChanged) and event.new == LinkState.FAULTY:
                self.faults += 1
            elif isinstance(event, Received) and isinstance(event.message, StatusQuery):
                self.answer_status()
            self.module_events.append(event)
        for event in self.base.events():
            if isinstance(event, StateChanged) and event.new == LinkState.FAULTY:
                self.base_faults += 1
            self.base_events.append(event)
        return now

    def answer_status(self) -> None:
        """As robot_change.service.core answers STATUS_QUERY: coalesced."""
        self.status_seq += 1
        self.module.send(Status(ModuleState.IDLE, frame_index=self.status_seq, station="kitchen"),
                         coalesce="status")

    def connect(self, corrupt: float) -> None:
        deadline = time.monotonic() + 5.0
        while not self.module.state == self.base.state == LinkState.UP:
            if self.pump() > deadline:
                raise LinkError("the two links did not connect over the pty pair within 5 s")
        self.pump()
        self.module_events.clear()
        self.base_events.clear()
        self.to_base.corrupt = self.to_module.corrupt = corrupt
        self.faults = self.base_faults = 0

    def wait(self, seconds: float, until: Any = None) -> float:
        end = time.monotonic() + seconds
        while True:
            now = self.pump()
            if until is not None and until():
                return now
            if now >= end:
                return now

    def settle(self) -> None:
        """Let what is in flight finish (at most the carry timeout), for honest counters."""
        self.wait(self.module.config.carry_timeout + 0.5,
                  lambda: not (self.module.in_flight or self.module.queued or self.base.in_flight
                               or self.base.queued))

    def totals(self, corrupt: float, baud: int) -> dict[str, Any]:
        m, b = self.module, self.base
        return {"retransmissions": m.stats.retransmissions + b.stats.retransmissions,
                "parts_sent": m.stats.parts_sent + b.stats.parts_sent,
                "bad_frames": m.decoder.errors + b.decoder.errors,
                "bytes": self.to_base.bytes + self.to_module.bytes,
                "corrupted_bytes": self.to_base.corrupted + self.to_module.corrupted,
                "link_faults": self.faults, "base_link_faults": self.base_faults,
                "corrupt": corrupt, "baud": baud,
                "seconds": round(time.monotonic() - self.start, 2)}

    # -- modes ------------------------------------------------------------------------------

    def run_pause(self, corrupt: float, count: int, timeout: float, gap: float, *_: Any
                  ) -> dict[str, Any]:
        self.connect(corrupt)
        rtts: list[float] = []
        one_way: list[float] = []
        got = failed = 0
        for _ in range(count):
            started = time.monotonic()
            seq = self.module.send(Pause(PauseCause.CHANGE_WATCH), started)
            heard: list[float] = []
            result: list[Any] = []

            def done(seq=seq, heard=heard, started=started, result=result) -> bool:
                for e in self.base_events:
                    if isinstance(e, Received) and isinstance(e.message, Pause) and e.seq == seq \
                            and not heard:
                        heard.append(time.monotonic() - started)
                self.base_events.clear()
                for e in self.module_events:
                    if isinstance(e, (Delivered, SendFailed)) and e.seq == seq:
                        result.append((e, time.monotonic() - started))
                self.module_events.clear()
                return bool(result)

            self.wait(timeout, done)
            got += bool(heard)
            one_way += heard
            if result and isinstance(result[0][0], Delivered):
                rtts.append(result[0][1])
            else:
                failed += 1
            self.wait(gap)
        return {"sent": count, "delivered": len(rtts), "received_by_base": got, "failed": failed,
                "p50_ms": _ms(_percentile(rtts, 50)), "p99_ms": _ms(_percentile(rtts, 99)),
                "max_ms": _ms(max(rtts) if rtts else None),
                "one_way_p50_ms": _ms(_percentile(one_way, 50)),
                "one_way_p99_ms": _ms(_percentile(one_way, 99))}

    def run_report(self, corrupt: float, count: int, timeout: float, gap: float, regions: int,
                   report_timeout: float) -> dict[str, Any]:
        self.connect(corrupt)
        wire_regions = _regions(regions, count)
        assembler = ReportAssembler()
        pauses = complete = resumes = 0
        latencies: list[float] = []
        for k in range(1, count + 1):
            started = time.monotonic()
            state: dict[str, Any] = {"pause_seq": self.answer_check(k, wire_regions, started),
                                     "pause": False, "report": None}
            self.wait(report_timeout,
                      lambda state=state, k=k, started=started:
                      self.answer_seen(state, k, started, assembler))
            pauses += state["pause"]
            if state["report"] is not None and state["report"] <= report_timeout:
                complete += 1
                latencies.append(state["report"])
            self.module_events.clear()
            resumes += self.resume(timeout)
            # what is still in flight for this report is left to finish or fail on its own
            self.wait(gap, lambda: not self.module.in_flight and not self.module.queued)
            self.module_events.clear()
        return {"sent": count, "regions": regions, "report_timeout_s": report_timeout,
                "pauses_received": pauses, "reports_complete": complete,
                "report_p50_ms": _ms(_percentile(latencies, 50)),
                "report_p99_ms": _ms(_percentile(latencies, 99)),
                "report_max_ms": _ms(max(latencies) if latencies else None),
                "resumes_delivered": resumes}

    def answer_check(self, k: int, regions: list[Region], now: float) -> int:
        """Answer check ``k`` as the service does: PAUSE, CHECK_RESULT (version >= 2), the
        report's parts; the PAUSE's seq."""
        pause_seq = self.module.send(Pause(PauseCause.CHANGE_CHECK), now)
        if self.module.version >= 2:
            self.module.send(CheckResult("kitchen", CheckOutcome.CHANGED, k), now)
        for part in split_change_report(k, "kitchen", regions):
            self.module.send(part, now)
        return pause_seq

    def answer_seen(self, state: dict[str, Any], k: int, started: float,
                    assembler: ReportAssembler) -> bool:
        """Take the base's events: PAUSE ``state["pause_seq"]`` received, report ``k`` joined
        (``state["report"]``: seconds since ``started``); whether both are there."""
        for e in self.base_events:
            if not isinstance(e, Received):
                continue
            if isinstance(e.message, Pause) and e.seq == state["pause_seq"]:
                state["pause"] = True
            elif (isinstance(e.message, ChangeReport) and e.message.report_id == k
                  and assembler.add(e.message) is not None):
                state["report"] = time.monotonic() - started
        self.base_events.clear()
        return state["report"] is not None and state["pause"]

    def resume(self, timeout: float) -> bool:
        """The base sends RESUME; whether it was acknowledged within ``timeout``."""
        seq = self.base.send(Resume())
        result: list[Any] = []

        def resumed() -> bool:
            result.extend(e for e in self.base_events
                          if isinstance(e, (Delivered, SendFailed)) and e.seq == seq)
            self.base_events.clear()
            return bool(result)

        self.wait(timeout, resumed)
        return bool(result) and isinstance(result[0], Delivered)

    def run_check(self, corrupt: float, count: int, timeout: float, gap: float, regions: int,
                  report_timeout: float) -> dict[str, Any]:
        self.connect(corrupt)
        wire_regions = _regions(regions, count)
        assembler = ReportAssembler()
        reached = answered = resumes = 0
        latencies: list[float] = []
        for k in range(1, count + 1):
            started = time.monotonic()
            self.base.send(Check("kitchen"), started)
            state: dict[str, Any] = {"pause_seq": None, "pause": False, "report": None}

            def answered_whole(state=state, k=k, started=started) -> bool:
                for e in self.module_events:
                    if (isinstance(e, Received) and isinstance(e.message, Check)
                            and state["pause_seq"] is None):
                        state["pause_seq"] = self.answer_check(k, wire_regions, time.monotonic())
                self.module_events.clear()
                return self.answer_seen(state, k, started, assembler)

            self.wait(report_timeout, answered_whole)
            if state["report"] is not None and state["pause"]:
                answered += 1
                latencies.append(state["report"])
            # a CHECK still carried is left to arrive (or fail) before the next one
            self.wait(self.base.config.carry_timeout,
                      lambda: not self.base.in_flight and not self.base.queued)
            answered_whole()
            reached += state["pause_seq"] is not None
            resumes += self.resume(timeout)
            self.wait(gap, lambda: not self.module.in_flight and not self.module.queued)
            self.module_events.clear()
        return {"sent": count, "regions": regions, "report_timeout_s": report_timeout,
                "reached": reached, "answered": answered,
                "answer_p50_ms": _ms(_percentile(latencies, 50)),
                "answer_p99_ms": _ms(_percentile(latencies, 99)),
                "answer_max_ms": _ms(max(latencies) if latencies else None),
                "resumes_delivered": resumes}

    def run_restart(self, corrupt: float, count: int, timeout: float, gap: float, regions: int,
                    report_timeout: float) -> dict[str, Any]:
        self.connect(corrupt)
        rng = random.Random(count)
        seen: list[float] = []
        ready: list[float] = []
        for _ in range(count):
            self.module_off = True  # stopped: silent and deaf until it starts again
            self.wait(RESTART_SILENCE)
            self.module, self.module_off = self.new_module(), False
            started = time.monotonic()
            state: dict[str, float] = {}

            def known(boot=self.module.boot_id, state=state, started=started) -> bool:
                now = time.monotonic()
                for e in self.base_events:
                    if (isinstance(e, Received) and isinstance(e.message, Hello)
                            and e.message.boot_id == boot and "seen" not in state):
                        state["seen"] = now - started
                self.base_events.clear()
                if ("ready" not in state and self.module.state == LinkState.UP
                        and self.module.version == self.base.version == self.proto):
                    state["ready"] = now - started
                return len(state) == 2

            self.wait(report_timeout, known)
            if "seen" in state:
                seen.append(state["seen"])
            if "ready" in state:
                ready.append(state["ready"])
            self.module_events.clear()
            self.wait(rng.uniform(0.2, 0.5))  # up a while before the next restart
        return {"sent": count, "timeout_s": report_timeout, "seen": len(seen),
                "seen_p50_ms": _ms(_percentile(seen, 50)),
                "seen_p99_ms": _ms(_percentile(seen, 99)),
                "seen_max_ms": _ms(max(seen) if seen else None), "ready": len(ready),
                "ready_p50_ms": _ms(_percentile(ready, 50)),
                "ready_p99_ms": _ms(_percentile(ready, 99))}

    def run_idle(self, corrupt: float, count: int, *_: Any) -> dict[str, Any]:
        self.connect(corrupt)
        self.wait(float(count))
        return {"sent": count}

    def run_status(self, corrupt: float, count: int, timeout: float, gap: float, *_: Any
                   ) -> dict[str, Any]:
        self.connect(corrupt)
        answered = 0
        latencies: list[float] = []
        for _ in range(count):
            started = time.monotonic()
            self.base.send(StatusQuery(), started)
            got: list[float] = []

            def answer(got=got, started=started) -> bool:
                if any(isinstance(e, Received) and isinstance(e.message, Status)
                       for e in self.base_events):
                    got.append(time.monotonic() - started)
                self.base_events.clear()
                return bool(got)

            self.wait(timeout, answer)
            if got:
                answered += 1
                latencies.append(got[0])
            self.wait(gap, lambda: not self.module.in_flight and not self.module.queued)
            self.base_events.clear()
            self.module_events.clear()
        return {"sent": count, "answered": answered, "timeout_s": timeout,
                "status_p50_ms": _ms(_percentile(latencies, 50)),
                "status_p99_ms": _ms(_percentile(latencies, 99))}

    def run_flood(self, corrupt: float, count: int, *_: Any) -> dict[str, Any]:
        self.connect(corrupt)
        for _ in range(count):
            self.base.send(StatusQuery())
        self.wait(600.0, lambda: not self.base.in_flight and not self.base.queued)
        self.settle()
        acked = sum(isinstance(e, Delivered) for e in self.base_events)
        refused = sum(isinstance(e, SendFailed) and e.nak is not None for e in self.base_events)
        failed = sum(isinstance(e, SendFailed) and e.nak is None for e in self.base_events)
        statuses = sum(isinstance(e, Received) and isinstance(e.message, Status)
                       for e in self.base_events)
        dropped = sum(isinstance(e, SendFailed) for e in self.module_events)
        return {"sent": count, "acked": acked, "refused": refused, "failed": failed,
                "status_received": statuses, "answers_dropped": dropped}


def _regions(count: int, seed: int) -> list[Region]:
    """``count`` made-up regions of a change report (the same for one ``seed``)."""
    rng = random.Random(seed)
    return [Region(RegionKind.APPEARED, (rng.randrange(-3000, 3000), rng.randrange(-3000, 3000),
                                         rng.randrange(0, 2000)),
                   (rng.randrange(10, 2000),) * 3, rng.randrange(12, 50000))
            for _ in range(count)]


def median_of(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """The median of each numeric figure over several runs (for docs/benchmarks.md)."""
    out = dict(runs[0])
    for key, value in runs[0].items():
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            values = [r[key] for r in runs if r.get(key) is not None]
            out[key] = statistics.median(values) if values else None
    out["runs"] = len(runs)
    return out
