"""``robot-change link-bench``: PAUSE round trips through a noisy, baud-paced serial line.

Two pseudo-terminal pairs joined by a relay: module Link <-> pyserial port <-> pty <-> relay <->
pty <-> pyserial port <-> base Link.  The relay lets bytes through at the line's pace (baud / 10
bytes per second, 8N1) and corrupts each byte with probability ``corrupt`` (XOR with a random
non-zero value: bit flips, false delimiters, lost delimiters).  The links connect over a clean
line; then the noise is switched on and the module sends ``count`` PAUSEs, one at a time.

A round trip counts as delivered when the base received the PAUSE and the module received its
ACK; its latency is from ``send()`` to that ACK.  Everything runs in one thread (select), so the
figures are the protocol's, not the scheduler's.
"""

from __future__ import annotations

import json as _json
import os
import random
import select
import sys
import time
import tty
from collections import deque
from typing import Any, TextIO

from hw.serial_port import open_port
from robot_change.errors import InputError, LinkError
from robot_change.link.protocol import (
    BaseHeartbeat,
    Heartbeat,
    ModuleState,
    Motion,
    Pause,
    PauseCause,
    Role,
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


class _Direction:
    """One direction of the relay: paced, corrupting, writing to a pty master."""

    def __init__(self, fd_out: int, byte_rate: float, rng: random.Random) -> None:
        self.fd_out = fd_out
        self.byte_rate = byte_rate
        self.rng = rng
        self.corrupt = 0.0
        self.queue: deque[tuple[float, int]] = deque()
        self.free_at = 0.0
        self.bytes = 0
        self.corrupted = 0

    def push(self, data: bytes, now: float) -> None:
        start = max(self.free_at, now)
        for i, byte in enumerate(data):
            if self.corrupt and self.rng.random() < self.corrupt:
                byte ^= self.rng.randrange(1, 256)
                self.corrupted += 1
            self.queue.append((start + (i + 1) / self.byte_rate, byte))
        self.free_at = start + len(data) / self.byte_rate
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
                   out: TextIO | None = None) -> dict[str, Any]:
    """Run the bench; print the result (one JSON object with ``json``) and return it as a dict.

    Keys: sent, delivered, received_by_base, failed, p50_ms, p99_ms, max_ms (round trips),
    one_way_p50_ms, one_way_p99_ms, retransmissions, bad_frames, bytes, corrupted_bytes,
    link_faults, corrupt, baud, seconds.
    """
    if not 0 <= corrupt < 1:
        raise InputError(f"--corrupt {corrupt}: give a probability per byte, 0 <= p < 1")
    if not 1 <= count <= 1_000_000:
        raise InputError(f"--count {count}: give 1..1000000 round trips")
    if not 300 <= baud <= 4_000_000:
        raise InputError(f"--baud {baud}: give 300..4000000")
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
        to_base = _Direction(mb, baud / 10, rng)
        to_module = _Direction(ma, baud / 10, rng)
        config = LinkConfig.for_baud(baud)
        module, base = Link(Role.MODULE, config=config), Link(Role.BASE, config=config)
        module.set_heartbeat(Heartbeat(ModuleState.WATCHING, paused=True, armed=True, fps_x10=300))
        base.set_heartbeat(BaseHeartbeat(Motion.PARKED))
        return _run(module, base, port_m, port_b, ma, mb, to_base, to_module, corrupt, count,
                    baud, timeout, gap, json, out)
    finally:
        for port in ports:
            port.close()
        for fd in fds:
            os.close(fd)


def _run(module: Link, base: Link, port_m: Any, port_b: Any, ma: int, mb: int,
         to_base: _Direction, to_module: _Direction, corrupt: float, count: int, baud: int,
         timeout: float, gap: float, as_json: bool, out: TextIO) -> dict[str, Any]:
    fd_m, fd_b = port_m.fileno(), port_b.fileno()
    rtts: list[float] = []
    one_way: list[float] = []
    received_by_base: set[int] = set()
    sent = failed = faults = 0
    current: int | None = None
    started = next_start = 0.0
    bench_start = time.monotonic()
    connect_deadline = bench_start + 5.0
    while True:
        now = time.monotonic()
        for link, port in ((module, port_m), (base, port_b)):
            link.poll(now)
            data = link.outgoing()
            if data:
                port.write(data)
        to_base.flush(now)
        to_module.flush(now)
        for event in base.events():
            if isinstance(event, Received) and isinstance(event.message, Pause) and current is not None \
                    and event.seq == current and current not in received_by_base:
                received_by_base.add(current)
                one_way.append(now - started)
        for event in module.events():
            if isinstance(event, StateChanged) and event.new == LinkState.FAULTY:
                faults += 1
            elif isinstance(event, (Delivered, SendFailed)) and event.seq == current:
                if isinstance(event, Delivered):
                    rtts.append(now - started)
                else:
                    failed += 1
                current, next_start = None, now + gap
        if to_base.corrupt == 0 and corrupt and module.state == base.state == LinkState.UP:
            to_base.corrupt = to_module.corrupt = corrupt
            next_start = now
        if module.state != LinkState.UP and sent == 0 and now > connect_deadline:
            raise LinkError("the two links did not connect over the pty pair within 5 s")
        ready = module.state == base.state == LinkState.UP or sent > 0
        if current is None and ready and (to_base.corrupt or not corrupt) and now >= next_start:
            if sent == count:
                break
            current, started = module.send(Pause(PauseCause.CHANGE_WATCH), now), now
            sent += 1
            continue
        if current is not None and now - started > timeout:
            failed += 1  # neither ACK nor failure in time: count it as lost
            current, next_start = None, now + gap
        deadline = min(module.next_deadline(), base.next_deadline(), to_base.next_due(),
                       to_module.next_due(), now + 0.01)
        readable, _, _ = select.select([fd_m, fd_b, ma, mb], [], [], max(0.0, deadline - now))
        now = time.monotonic()
        for fd in readable:
            if fd == fd_m:
                module.receive(port_m.read(port_m.in_waiting or 1), now)
            elif fd == fd_b:
                base.receive(port_b.read(port_b.in_waiting or 1), now)
            else:
                try:
                    data = os.read(fd, 4096)
                except BlockingIOError:
                    continue
                (to_base if fd == ma else to_module).push(data, now)
    result = {
        "sent": sent,
        "delivered": len(rtts),
        "received_by_base": len(received_by_base),
        "failed": failed,
        "p50_ms": _ms(_percentile(rtts, 50)),
        "p99_ms": _ms(_percentile(rtts, 99)),
        "max_ms": _ms(max(rtts) if rtts else None),
        "one_way_p50_ms": _ms(_percentile(one_way, 50)),
        "one_way_p99_ms": _ms(_percentile(one_way, 99)),
        "retransmissions": module.stats.retransmissions,
        "bad_frames": module.decoder.errors + base.decoder.errors,
        "bytes": to_base.bytes + to_module.bytes,
        "corrupted_bytes": to_base.corrupted + to_module.corrupted,
        "link_faults": faults,
        "corrupt": corrupt,
        "baud": baud,
        "seconds": round(time.monotonic() - bench_start, 2),
    }
    if as_json:
        print(_json.dumps(result), file=out)
    else:
        pct = 100.0 * result["delivered"] / sent if sent else 0.0
        print(f"PAUSE round trips at {baud} baud, {corrupt:.0%} of bytes corrupted: "
              f"sent {sent}, delivered {result['delivered']} ({pct:.1f}%), "
              f"p50 {result['p50_ms']} ms, p99 {result['p99_ms']} ms, max {result['max_ms']} ms; "
              f"{result['retransmissions']} retransmissions, {result['bad_frames']} bad frames, "
              f"{result['link_faults']} link faults", file=out)
    return result
