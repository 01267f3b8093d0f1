"""robot_change.link.session: the session, stepped with a fake clock; then over a real pty pair."""

from __future__ import annotations

import os
import random
import time
import tty

import pytest

from hw.serial_port import FdPort
from robot_change.errors import LinkError
from robot_change.link import protocol as p
from robot_change.link.session import (
    Delivered,
    Link,
    LinkConfig,
    LinkRunner,
    LinkState,
    Received,
    SendFailed,
    StateChanged,
)
from tests.test_protocol import raw_frame


class Clock:
    """A clock that moves only when told."""

    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def frames(data: bytes) -> list[p.Frame]:
    return [x for x in p.FrameDecoder().feed(data) if isinstance(x, p.Frame)]


class Wire:
    """Two links joined by an in-memory line; ``noise`` corrupts each byte with that probability."""

    def __init__(self, noise: float = 0.0, seed: int = 1, proto_max: int = p.VERSION) -> None:
        """``proto_max``: what the base offers (2: the module sends whole frames, 3: PARTs)."""
        self.clock = Clock()
        self.module = Link(p.Role.MODULE, clock=self.clock, boot_id=0xAAAA)
        self.base = Link(p.Role.BASE, clock=self.clock, boot_id=0xBBBB, proto_max=proto_max)
        self.noise = noise
        self.rng = random.Random(seed)
        self.cut = False  # True: the base hears nothing and says nothing
        self.module_events: list = []
        self.base_events: list = []

    def corrupt(self, data: bytes) -> bytes:
        if not self.noise:
            return data
        out = bytearray(data)
        for i in range(len(out)):
            if self.rng.random() < self.noise:
                out[i] ^= self.rng.randrange(1, 256)
        return bytes(out)

    def step(self, dt: float = 0.0) -> None:
        self.clock.t += dt
        for _ in range(3):
            self.module.poll()
            self.base.poll()
            to_base, to_module = self.module.outgoing(), self.base.outgoing()
            if not self.cut:
                self.base.receive(self.corrupt(to_base))
                self.module.receive(self.corrupt(to_module))
        self.module_events += self.module.events()
        self.base_events += self.base.events()

    def run(self, seconds: float, dt: float = 0.01) -> None:
        for _ in range(round(seconds / dt)):
            self.step(dt)

    def connect(self) -> Wire:
        self.step()
        assert self.module.state == self.base.state == LinkState.UP
        self.module_events.clear()
        self.base_events.clear()
        return self


def received(events, cls=None):
    return [e.message for e in events if isinstance(e, Received)
            and (cls is None or isinstance(e.message, cls))]


# -- handshake -------------------------------------------------------------------------------


def test_hello_exchange_brings_both_ends_up():
    wire = Wire()
    wire.step()
    assert wire.module.state == wire.base.state == LinkState.UP
    (hello,) = received(wire.base_events, p.Hello)
    assert (hello.role, hello.boot_id, hello.proto_min, hello.proto_max) == \
        (p.Role.MODULE, 0xAAAA, 1, p.VERSION)
    assert wire.module.version == wire.base.version == p.VERSION
    assert wire.module.peer.boot_id == 0xBBBB
    assert any(isinstance(e, StateChanged) and e.new == LinkState.UP for e in wire.module_events)


def test_nothing_but_hello_and_heartbeats_before_the_first_hello_is_acked():
    clock = Clock()
    link = Link(p.Role.MODULE, clock=clock)
    link.set_heartbeat(p.Heartbeat(p.ModuleState.IDLE))
    link.send(p.Clear("kitchen"))
    link.send(p.Pause(p.PauseCause.CHANGE_CHECK))
    link.poll()
    kinds = {f.message.TYPE for f in frames(link.outgoing())}
    assert kinds == {p.MsgType.HELLO, p.MsgType.HEARTBEAT}
    assert link.queued == 2


def test_hello_is_retried_then_probed_every_hello_interval():
    clock = Clock()
    link = Link(p.Role.MODULE, clock=clock)
    sent_at = []
    for _ in range(150):  # 1.5 s, nobody answers
        link.poll()
        if any(f.message.TYPE == p.MsgType.HELLO for f in frames(link.outgoing())):
            sent_at.append(round(clock.t - 100.0, 2))
        clock.t += 0.01
    assert sent_at[:5] == [0.0, 0.1, 0.2, 0.3, 0.4]
    assert sent_at[5] == pytest.approx(1.0)  # 5 tries, give up at 0.5, next attempt 0.5 s later
    assert link.state == LinkState.CONNECTING
    assert not [e for e in link.events() if isinstance(e, SendFailed)]  # HELLO is the link's own


# -- acks, retries, FAULTY -----------------------------------------------------------------------


def test_message_is_delivered_once_and_acked():
    wire = Wire().connect()
    seq = wire.module.send(p.Clear("kitchen"))
    wire.step()
    assert received(wire.base_events) == [p.Clear("kitchen")]
    (done,) = [e for e in wire.module_events if isinstance(e, Delivered)]
    assert (done.seq, done.tries, done.message) == (seq, 1, p.Clear("kitchen"))


def test_five_unanswered_tries_100ms_apart_then_faulty():
    wire = Wire(proto_max=2).connect()  # whole frames (version 3 carries them in PARTs)
    wire.cut = True
    seq = wire.module.send(p.Clear("kitchen"))
    tries = []
    for _ in range(70):
        wire.module.poll()
        if any(f.seq == seq and f.message.TYPE == p.MsgType.CLEAR
               for f in frames(wire.module.outgoing())):
            tries.append(round(wire.clock.t - 100.0, 2))
        wire.clock.t += 0.01
    events = wire.module.events()
    assert tries == [0.0, 0.1, 0.2, 0.3, 0.4]
    (failed,) = [e for e in events if isinstance(e, SendFailed)]
    assert failed.seq == seq and "5 tries" in failed.reason and failed.nak is None
    (change,) = [e for e in events if isinstance(e, StateChanged)]
    assert change.new == LinkState.FAULTY and "base is running" in change.why


def test_retransmissions_carry_the_retry_flag_and_recovery_goes_back_up():
    wire = Wire(proto_max=2).connect()  # whole frames (version 3 carries them in PARTs)
    wire.cut = True
    wire.module.send(p.Clear("kitchen"))
    flags = []
    for _ in range(6):
        wire.module.poll()
        flags += [f.flags for f in frames(wire.module.outgoing())
                  if f.message.TYPE == p.MsgType.CLEAR]
        wire.clock.t += 0.1
    assert flags == [0] + [p.FLAG_RETRY] * 4
    assert wire.module.state == LinkState.FAULTY
    wire.cut = False
    wire.run(0.6)
    assert wire.module.state == LinkState.UP
    seq = wire.module.send(p.Clear("hall"))
    wire.step()
    assert any(isinstance(e, Delivered) and e.seq == seq for e in wire.module_events)


def test_peer_silence_makes_the_link_faulty():
    wire = Wire().connect()
    wire.module.set_heartbeat(p.Heartbeat(p.ModuleState.IDLE))
    wire.cut = True
    wire.run(0.95)
    assert wire.module.state == LinkState.UP
    wire.run(0.1)
    assert wire.module.state == LinkState.FAULTY
    (change,) = [e for e in wire.module_events if isinstance(e, StateChanged)]
    assert "nothing heard from the base" in change.why


def test_window_limits_messages_in_flight():
    wire = Wire(proto_max=2).connect()  # whole frames (version 3 carries them in PARTs)
    wire.cut = True
    for i in range(10):
        wire.module.send(p.Clear(f"s{i}"))
    wire.module.poll()
    assert len(frames(wire.module.outgoing())) == 4
    assert wire.module.in_flight == 4 and wire.module.queued == 6
    wire.cut = False
    wire.run(0.6)
    assert sorted(m.station for m in received(wire.base_events, p.Clear)) == \
        [f"s{i}" for i in range(10)]


def test_queue_is_bounded():
    clock = Clock()
    link = Link(p.Role.MODULE, clock=clock, config=LinkConfig(max_queue=3))
    for i in range(5):
        link.send(p.Clear(f"s{i}"))
    failed = [e for e in link.events() if isinstance(e, SendFailed)]
    assert [e.message.station for e in failed] == ["s0", "s1"]
    assert "queue full" in failed[0].reason


# -- duplicates ---------------------------------------------------------------------------------


def test_duplicates_are_acked_again_but_delivered_once():
    wire = Wire(proto_max=2).connect()  # whole frames (version 3 carries them in PARTs)
    wire.module.send(p.Clear("kitchen"))
    data = wire.module.outgoing()
    for _ in range(3):
        wire.base.receive(data)
    acks = [f for f in frames(wire.base.outgoing()) if f.message.TYPE == p.MsgType.ACK]
    assert len(acks) == 3 and len({f.seq for f in acks}) == 1
    assert received(wire.base.events()) == [p.Clear("kitchen")]
    assert wire.base.stats.duplicates == 2


def test_a_restarted_peer_is_not_mistaken_for_duplicates():
    wire = Wire().connect()
    wire.module.send(p.Clear("a"))
    wire.step()
    # the module restarts: new boot id, seqs start again at 1
    wire.module = Link(p.Role.MODULE, clock=wire.clock, boot_id=0xCCCC)
    wire.base_events.clear()
    wire.step()
    wire.module.send(p.Clear("b"))
    wire.step()
    assert received(wire.base_events, p.Clear) == [p.Clear("b")]


def test_urgent_messages_go_out_as_bursts_and_are_answered_by_one_ack_burst():
    wire = Wire().connect()
    seq = wire.module.send(p.Pause(p.PauseCause.CHANGE_WATCH))
    out = frames(wire.module.outgoing())  # send() transmits at once
    assert len(out) == p.URGENT_COPIES
    assert all(f.seq == seq and f.flags == p.FLAG_URGENT for f in out)
    wire.base.receive(b"".join(p.encode(f.message, f.seq, f.flags) for f in out))
    acks = frames(wire.base.outgoing())
    assert len(acks) == p.URGENT_COPIES and {f.seq for f in acks} == {seq}
    wire.clock.t += 0.1  # the next try is answered with a fresh burst
    wire.base.receive(p.encode(out[0].message, seq, p.FLAG_URGENT | p.FLAG_RETRY))
    assert len(frames(wire.base.outgoing())) == p.URGENT_COPIES
    assert received(wire.base.events(), p.Pause) == [p.Pause(p.PauseCause.CHANGE_WATCH)]


def test_urgent_messages_skip_the_window():
    wire = Wire().connect()
    wire.cut = True
    for i in range(6):
        wire.module.send(p.Clear(f"s{i}"))
    wire.module.outgoing()
    wire.module.send(p.Pause(p.PauseCause.CHANGE_CHECK))
    assert {f.message.TYPE for f in frames(wire.module.outgoing())} == {p.MsgType.PAUSE}


# -- NAK --------------------------------------------------------------------------------------


@pytest.mark.parametrize("bad,reason", [
    (raw_frame(1, 0x7F, 33), p.NakReason.UNKNOWN_TYPE),
    (raw_frame(1, p.MsgType.CHECK, 33, payload=b"\x03../"), p.NakReason.BAD_PAYLOAD),
    (raw_frame(1, p.MsgType.SET_PARAM, 33, payload=b"\x01" + (99).to_bytes(4, "little")),
     p.NakReason.OUT_OF_RANGE),
    (raw_frame(1, p.MsgType.GET_PARAM, 33, payload=b"\xee"), p.NakReason.UNKNOWN_PARAM),
    (raw_frame(p.VERSION + 1, p.MsgType.CHECK, 33, payload=b"\x01k"), p.NakReason.BAD_VERSION),
    (p.encode(p.Pause(p.PauseCause.CHANGE_CHECK), 33), p.NakReason.WRONG_DIRECTION),
    (p.encode(p.Hello(p.Role.MODULE, 5), 33), p.NakReason.WRONG_DIRECTION),
])
def test_refused_frames_get_a_nak_with_reason_seq_and_type(bad, reason):
    clock = Clock()
    module = Link(p.Role.MODULE, clock=clock)
    module.outgoing()
    module.receive(bad)
    (nak,) = frames(module.outgoing())
    assert nak.message.TYPE == p.MsgType.NAK and nak.seq == 33
    assert nak.message.reason == reason
    # the type byte of the refused frame
    assert nak.message.refused_type == p.cobs_decode(bad[:-1])[1]
    assert not received(module.events(), p.Check)


@pytest.mark.parametrize("bad", [
    b"\x05\x01\x00",                                        # bad COBS
    p.encode(p.Check("k"), 4)[:-3] + b"\x99\x99\x00",       # bad CRC: header not trusted
    raw_frame(1, p.MsgType.ACK, 4, payload=b"\x01"),        # a bad ACK is never NAKed
    raw_frame(1, p.MsgType.NAK, 4, payload=b"\x01"),        # nor a bad NAK
])
def test_no_nak_where_none_is_due(bad):
    module = Link(p.Role.MODULE, clock=Clock())
    module.outgoing()
    module.receive(bad)
    assert module.outgoing() == b""


@pytest.mark.parametrize("proto", [4, p.VERSION])
def test_a_nak_fails_the_message_without_faulting_the_link(proto):
    wire = Wire(proto_max=proto).connect()
    seq = wire.base.send(p.SetParam(1, 3))
    wire.base.poll()  # version 5: the carousel writes the command's PARTs
    data = wire.base.outgoing()
    assert frames(data)[0].seq == seq
    wire.base.receive(p.encode(p.Nak(p.NakReason.OUT_OF_RANGE, p.MsgType.SET_PARAM), seq))
    (failed,) = [e for e in wire.base.events() if isinstance(e, SendFailed)]
    assert failed.nak == p.NakReason.OUT_OF_RANGE and failed.seq == seq
    assert wire.base.state == LinkState.UP and wire.base.in_flight == 0


def test_incompatible_versions_are_reported():
    module = Link(p.Role.MODULE, clock=Clock())
    low, high = p.VERSION + 1, p.VERSION + 2
    module.receive(p.encode(p.Hello(p.Role.BASE, 9, "fw", proto_min=low, proto_max=high), 1))
    (change,) = [e for e in module.events() if isinstance(e, StateChanged)]
    assert change.new == LinkState.INCOMPATIBLE and f"{low}..{high}" in change.why


def test_an_incompatible_hello_is_naked_and_the_module_goes_quiet_until_one_that_meets():
    """Issue 46, item 3: the base learns it (NAK BAD_VERSION of its HELLO, not an ACK); the
    module sends nothing the base refused to read (no heartbeat) until a HELLO whose versions
    meet (the base updated), which it acknowledges, greeting the base again."""
    clock = Clock()
    module = Link(p.Role.MODULE, clock=clock, boot_id=0xAAAA)
    module.set_heartbeat(p.Heartbeat(p.ModuleState.IDLE))
    module.poll()
    module.outgoing()  # its HELLO and first heartbeat
    too_new = p.Hello(p.Role.BASE, 9, "fw", proto_min=p.VERSION + 1, proto_max=p.VERSION + 2)
    module.receive(p.encode(too_new, 1))
    (answer,) = frames(module.outgoing())
    assert answer.message == p.Nak(p.NakReason.BAD_VERSION, p.MsgType.HELLO) and answer.seq == 1
    assert module.state == LinkState.INCOMPATIBLE
    for _ in range(20):  # a second: no heartbeat; only its own HELLO's tries (any peer reads
        clock.t += 0.05  # a HELLO: it tells the base this end's versions)
        module.poll()
    assert {f.message.TYPE for f in frames(module.outgoing())} <= {p.MsgType.HELLO}
    updated = p.Hello(p.Role.BASE, 10, "fw 2", proto_min=1, proto_max=p.VERSION)
    module.receive(p.encode(updated, 1))
    out = frames(module.outgoing())
    assert [f.message.TYPE for f in out][:1] == [p.MsgType.ACK] and out[0].seq == 1
    hello = [f for f in out if f.message.TYPE == p.MsgType.HELLO]
    if not hello:  # its first HELLO was still in flight: its retry greets the base
        clock.t += 0.2
        module.poll()
        hello = [f for f in frames(module.outgoing()) if f.message.TYPE == p.MsgType.HELLO]
    module.receive(p.encode(p.Ack(), hello[0].seq))
    assert module.state == LinkState.UP and module.version == p.VERSION
    clock.t += 0.2
    module.poll()
    assert p.MsgType.HEARTBEAT in [f.message.TYPE for f in frames(module.outgoing())]


@pytest.mark.parametrize("header_version", [1, 2])
def test_a_newer_base_offering_1_to_2_is_answered_and_agrees_on_2(header_version):
    # the bug of issue 12: a HELLO whose header says 2 and offers 1..2 was refused
    module = Link(p.Role.MODULE, clock=Clock())
    module.receive(p.encode(p.Hello(p.Role.BASE, 9, "fw", 1, 2), 1, version=header_version))
    assert module.state != LinkState.INCOMPATIBLE and module.version == 2
    out = frames(module.outgoing())
    assert any(f.message.TYPE == p.MsgType.ACK for f in out)


def test_an_older_base_speaking_only_1_still_works():
    clock = Clock()
    module = Link(p.Role.MODULE, clock=clock, boot_id=1)
    base = Link(p.Role.BASE, clock=clock, boot_id=2, proto_max=1)
    for _ in range(20):
        module.poll()
        base.poll()
        base.receive(module.outgoing())
        module.receive(base.outgoing())
        clock.t += 0.01
    assert module.state == base.state == LinkState.UP and module.version == base.version == 1
    with pytest.raises(LinkError, match="version 2"):
        module.send(p.CheckResult("kitchen", p.CheckOutcome.NO_CHANGE))
    module.send(p.Clear("kitchen"))
    for _ in range(5):
        module.poll()
        base.receive(module.outgoing())
        module.receive(base.outgoing())
        clock.t += 0.01
    assert [e.message for e in base.events() if isinstance(e, Received)
            and isinstance(e.message, p.Clear)] == [p.Clear("kitchen")]
    # a v2 frame reaching an end that offers only 1 is refused, not read
    base.receive(p.encode(p.CheckResult("kitchen", p.CheckOutcome.NO_CHANGE), 40))
    naks = [f.message for f in frames(base.outgoing()) if f.message.TYPE == p.MsgType.NAK]
    assert naks and naks[0].reason == p.NakReason.BAD_VERSION


def test_garbage_into_the_link_never_crashes():
    rng = random.Random(8)
    module = Link(p.Role.MODULE, clock=Clock())
    for _ in range(300):
        module.receive(bytes(rng.randrange(256) for _ in range(rng.randint(0, 60))))
        module.poll()
    module.outgoing()
    counters = module.counters()
    assert module.decoder.errors > 0
    assert sum(v for k, v in counters.items() if k.startswith("decode_")) == module.decoder.errors


# -- roles ------------------------------------------------------------------------------------


@pytest.mark.parametrize("role,message,needle", [
    (p.Role.MODULE, p.Check("k"), "sent by the base"),
    (p.Role.BASE, p.Pause(1), "sent by the module"),
    (p.Role.MODULE, p.Heartbeat(p.ModuleState.IDLE), "set_heartbeat"),
    (p.Role.MODULE, p.Ack(), "the link sends it itself"),
    (p.Role.MODULE, p.Hello(p.Role.MODULE, 1), "the link sends it itself"),
])
def test_misuse_raises_link_error(role, message, needle):
    with pytest.raises(LinkError, match=needle):
        Link(role, clock=Clock()).send(message)
    with pytest.raises(LinkError, match="sends BASE_HEARTBEAT"):
        Link(p.Role.BASE, clock=Clock()).set_heartbeat(p.Heartbeat(p.ModuleState.IDLE))


# -- heartbeats -----------------------------------------------------------------------------


def test_heartbeats_every_100ms_and_at_once_when_they_change():
    clock = Clock()
    link = Link(p.Role.MODULE, clock=clock)
    link.set_heartbeat(p.Heartbeat(p.ModuleState.WATCHING))
    times = []
    for i in range(100):  # 1 s in 10 ms steps
        if i == 55:
            link.set_heartbeat(p.Heartbeat(p.ModuleState.WATCHING, paused=True))
        link.poll()
        times += [round(clock.t - 100, 2) for f in frames(link.outgoing())
                  if f.message.TYPE == p.MsgType.HEARTBEAT]
        clock.t += 0.01
    assert times == [0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.55, 0.65, 0.75, 0.85, 0.95]


def test_the_pause_latch_reaches_the_base_in_heartbeats_even_when_pause_fails():
    wire = Wire().connect()
    wire.module.set_heartbeat(p.Heartbeat(p.ModuleState.WATCHING, paused=True))
    wire.run(0.3)
    beats = received(wire.base_events, p.Heartbeat)
    assert len(beats) in (3, 4) and all(b.paused for b in beats)


# -- noise ------------------------------------------------------------------------------------


def test_pause_gets_through_10_percent_byte_corruption_by_retries():
    wire = Wire(seed=4).connect()  # a 35-byte HELLO rarely survives 10%: connect first
    wire.noise = 0.10
    delivered, sent = 0, 40
    for _ in range(sent):
        seq = wire.module.send(p.Pause(p.PauseCause.CHANGE_WATCH))
        for _ in range(60):
            wire.step(0.01)
            if any(isinstance(e, (Delivered, SendFailed)) and e.seq == seq
                   for e in wire.module_events):
                break
        delivered += any(isinstance(e, Delivered) and e.seq == seq for e in wire.module_events)
    assert delivered == sent
    assert len(received(wire.base_events, p.Pause)) == sent  # each exactly once at the base
    assert wire.module.stats.retransmissions > 0  # the noise did bite
    assert wire.base.decoder.errors > 0


# -- over a real pty pair -----------------------------------------------------------------------


def test_runner_over_a_pty_pair_delivers_pause_and_heartbeats():
    from hw.serial_port import open_port

    master, slave = os.openpty()
    tty.setraw(slave)
    port = open_port(os.ttyname(slave), timeout=0.01)
    os.close(slave)
    try:
        module = LinkRunner(Link(p.Role.MODULE), port)
        base = LinkRunner(Link(p.Role.BASE), FdPort(master))
        module.set_heartbeat(p.Heartbeat(p.ModuleState.WATCHING, paused=True))
        base.set_heartbeat(p.BaseHeartbeat(p.Motion.PARKED))
        got_module, got_base = [], []
        deadline = time.monotonic() + 3.0
        sent = None
        while time.monotonic() < deadline:
            got_module += module.step(0.005)
            got_base += base.step(0.005)
            if sent is None and module.link.state == LinkState.UP:
                sent = module.send(p.Pause(p.PauseCause.CHANGE_CHECK))
            if any(isinstance(e, Delivered) and e.seq == sent for e in got_module):
                break
        assert sent is not None, "the link never came up over the pty"
        assert any(isinstance(e, Delivered) and e.seq == sent for e in got_module)
        assert received(got_base, p.Pause) == [p.Pause(p.PauseCause.CHANGE_CHECK)]
        assert any(b.paused for b in received(got_base, p.Heartbeat))
        assert module.link.decoder.errors == base.link.decoder.errors == 0
    finally:
        port.close()
        os.close(master)


def test_link_bench_small_run_reports_every_figure():
    import io
    import json

    from robot_change.tools.linkbench import run_link_bench

    out = io.StringIO()
    result = run_link_bench(0.05, 5, 115200, json=True, seed=3, out=out)
    assert json.loads(out.getvalue()) == result
    assert result["sent"] == result["delivered"] == result["received_by_base"] == 5
    assert result["corrupted_bytes"] > 0 and \
        result["p50_ms"] <= result["p99_ms"] <= result["max_ms"]
    with pytest.raises(Exception, match="--corrupt"):
        run_link_bench(1.5, 5)


def test_config_for_slow_lines_keeps_retries_behind_the_bursts():
    fast = LinkConfig.for_baud(115200)
    assert (fast.retry_interval, fast.ack_holdoff) == (0.1, 0.05)  # the protocol's defaults
    slow = LinkConfig.for_baud(9600)
    air = 10 / 9600 * p.URGENT_COPIES * (10 + 9)  # a PAUSE burst and its ACK burst
    assert slow.retry_interval == pytest.approx(2.5 * air) and slow.retry_interval > 0.39
    assert slow.ack_holdoff == pytest.approx(1.5 * 10 / 9600 * p.URGENT_COPIES * 10)
    assert LinkConfig.for_baud(9600, max_tries=3).max_tries == 3


def test_every_port_the_module_is_handed_is_a_byte_port(tmp_path):
    """The typing of LinkRunner / Service: pyserial ports, ReopeningPort and FdPort fit."""
    import os

    from hw.serial_port import FdPort, ReopeningPort, open_port
    from robot_change.link.port import BytePort

    master, slave = os.openpty()
    try:
        assert isinstance(FdPort(master), BytePort)
        assert isinstance(open_port(os.ttyname(slave)), BytePort)
        assert isinstance(ReopeningPort(os.ttyname(slave)), BytePort)
        assert not isinstance(object(), BytePort)
    finally:
        os.close(master)
        os.close(slave)


# -- version 3: messages carried in PARTs (docs/protocol.md 7.11) -------------------------------


REGIONS = tuple(p.Region(p.RegionKind.APPEARED, (100 * i, 20, 3), (400, 300, 250), 700)
                for i in range(p.REGIONS_PER_PART))


def test_version_3_carries_module_messages_in_short_parts_and_acks_them_with_a_burst():
    wire = Wire().connect()
    report = p.ChangeReport(12, 0, 1, "kitchen", REGIONS)
    seq = wire.module.send(report)
    wire.module.poll()
    out = frames(wire.module.outgoing())
    assert out and all(f.message.TYPE == p.MsgType.PART and f.seq == seq for f in out)
    assert max(len(p.encode(f.message, f.seq, version=3)) for f in out) <= 19
    wire.base.receive(b"".join(p.encode(f.message, f.seq, version=3) for f in out))
    wire.run(0.5)
    assert received(wire.base_events, p.ChangeReport) == [report]  # once
    (done,) = [e for e in wire.module_events if isinstance(e, Delivered)]
    assert done.seq == seq and wire.module.in_flight == 0
    assert wire.base.stats.carried == 1


def test_parts_join_into_exactly_the_body_the_message_would_have_had():
    body = p.encode_body(p.ChangeReport(3, 0, 1, "hall", REGIONS[:4]), 9, 0, 3)
    parts = p.split_body(body)
    assert len(parts) == -(-len(body) // p.PART_DATA) and all(x.count == len(parts) for x in parts)
    assert b"".join(x.data for x in parts) == body


def test_the_base_asks_for_the_missing_parts_and_only_those_are_sent_again():
    wire = Wire().connect()
    seq = wire.module.send(p.Fault(p.FaultCode.CAMERA_LOST, "x" * 60))
    sent: list[p.Frame] = []
    for _ in range(10):  # 50 ms of the carousel, nothing reaches the base
        wire.clock.t += 0.005
        wire.module.poll()
        sent += frames(wire.module.outgoing())
    count = sent[0].message.count
    assert {f.message.index for f in sent} == set(range(count))
    keep = [f for f in sent if f.message.index not in (1, 4)]
    wire.base.receive(b"".join(p.encode(f.message, f.seq, version=3) for f in keep))
    wire.base.outgoing()  # its first NEED, sent at the first PART (at most one per 50 ms)
    wire.clock.t += wire.base.config.need_interval + 0.001
    wire.base.receive(p.encode(keep[0].message, keep[0].seq, version=3))  # a repeat
    (need,) = [f for f in frames(wire.base.outgoing()) if f.message.TYPE == p.MsgType.NEED]
    assert need.seq == seq and need.message.missing == (1, 4)
    wire.module.receive(p.encode(need.message, need.seq, version=3))
    again = []
    for _ in range(10):
        wire.clock.t += 0.005
        wire.module.poll()
        again += frames(wire.module.outgoing())
    assert again and {f.message.index for f in again} == {1, 4}


def test_a_need_for_no_piece_of_the_message_or_malformed_changes_nothing_and_is_never_naked():
    """Issue 46, points 7 and 8: one rule for a NEED naming no piece of its message (indices
    beyond its count) and for a malformed one (its bitmap's last byte zero): ignored, the
    carousel goes on with what it cycled, and no NAK (its seq is the module's message's)."""
    wire = Wire().connect()
    seq = wire.module.send(p.Fault(p.FaultCode.CAMERA_LOST, "x" * 60))

    def cycle() -> list[p.Frame]:
        out = []
        for _ in range(10):
            wire.clock.t += 0.005
            wire.module.poll()
            out += frames(wire.module.outgoing())
        return out

    count = cycle()[0].message.count
    wire.module.receive(p.encode(p.Need((1, 4)), seq, version=3))
    assert {f.message.index for f in cycle()} == {1, 4}
    for bad in (p.encode(p.Need((count, count + 3)), seq, version=3),
                raw_frame(3, p.MsgType.NEED, seq, payload=b"\x12\x00")):
        wire.module.receive(bad)
        out = cycle()
        assert not [f for f in out if f.message.TYPE == p.MsgType.NAK]
        assert {f.message.index for f in out if f.message.TYPE == p.MsgType.PART} == {1, 4}


def test_a_parted_message_is_retried_until_the_carry_timeout_then_the_link_is_faulty():
    wire = Wire().connect()
    wire.cut = True
    seq = wire.module.send(p.Clear("kitchen"))
    wire.run(wire.module.config.carry_timeout - 0.05)
    assert not [e for e in wire.module_events if isinstance(e, SendFailed)]
    assert wire.module.stats.parts_sent > 100  # the carousel kept going
    wire.run(0.1)
    (failed,) = [e for e in wire.module_events if isinstance(e, SendFailed)]
    assert failed.seq == seq and "PARTs" in failed.reason
    assert wire.module.state == LinkState.FAULTY


def test_a_new_boot_of_the_module_drops_half_joined_messages():
    wire = Wire().connect()
    wire.module.send(p.ChangeReport(1, 0, 1, "kitchen", REGIONS))
    wire.module.poll()
    first = frames(wire.module.outgoing())[:3]
    wire.base.receive(b"".join(p.encode(f.message, f.seq, version=3) for f in first))
    assert wire.base._assemblies
    wire.module = Link(p.Role.MODULE, clock=wire.clock, boot_id=0xCCCC)  # restarted
    wire.step()
    assert not wire.base._assemblies


@pytest.mark.parametrize("noise", [0.01, 0.10])
def test_reports_get_through_byte_corruption_in_parts(noise):
    wire = Wire(seed=7).connect()
    wire.noise = noise
    for k in range(1, 11):
        wire.module.send(p.ChangeReport(k, 0, 1, "kitchen", REGIONS[:k]))
    wire.run(10.0, dt=0.005)  # simulated seconds: 10 reports of 1..10 regions, 4 at a time
    got = received(wire.base_events, p.ChangeReport)
    assert sorted(r.report_id for r in got) == list(range(1, 11))  # each once, all complete
    assert wire.base.decoder.errors > 0 and \
        not [e for e in wire.module_events if isinstance(e, SendFailed)]


def test_admit_refuses_with_a_nak_and_the_message_is_not_remembered():
    busy = [True]
    wire = Wire()
    wire.module.admit = lambda m: p.NakReason.BUSY if busy[0] and isinstance(m, p.Check) else None
    wire.connect()
    seq = wire.base.send(p.Check("kitchen"))
    wire.step()
    (failed,) = [e for e in wire.base_events if isinstance(e, SendFailed)]
    assert failed.seq == seq and failed.nak == p.NakReason.BUSY
    assert not received(wire.module_events, p.Check)
    busy[0] = False
    wire.base.send(p.Check("kitchen"))
    wire.step()
    assert received(wire.module_events, p.Check) == [p.Check("kitchen")]


@pytest.mark.parametrize("proto", [3, p.VERSION])  # whole frame; carried in PARTs (v5)
def test_a_copy_of_a_refused_command_crossing_the_nak_gets_the_same_nak(proto):
    asked = []
    wire = Wire(proto_max=proto)
    wire.module.admit = lambda m: asked.append(m) or p.NakReason.BUSY
    wire.connect()
    seq = wire.base.send(p.Check("kitchen"))
    wire.base.poll()
    data = wire.base.outgoing()
    for _ in range(2):  # the command, then its retry sent before our NAK arrived
        wire.module.receive(data)
        naks = [f for f in frames(wire.module.outgoing()) if f.message.TYPE == p.MsgType.NAK]
        assert naks and {(f.seq, f.message.reason) for f in naks} == {(seq, p.NakReason.BUSY)}
    assert len(asked) == 1 and not received(wire.module.events(), p.Check)


@pytest.mark.parametrize("proto", [3, p.VERSION])  # whole frame; carried in PARTs (v5)
def test_a_seq_refused_for_its_content_keeps_its_nak_whatever_comes_with_it_again(proto):
    """docs/protocol.md 7.2: the module remembers how it answered a seq. A SET_PARAM NAKed
    OUT_OF_RANGE and sent again with the same seq and a good value is NAKed the same and not
    acted on (it was acted on: the base told two things about one seq)."""
    wire = Wire(proto_max=proto).connect()
    seq = 40
    good = p.encode_body(p.SetParam(1, 3), seq, 0, proto)  # watch_m = 3
    head = good[:6] + (10_000).to_bytes(4, "little")  # watch_m = 10000: out of range
    bad = head + p.crc16(head).to_bytes(2, "big")
    for body in (bad, good):
        wire.module.receive(p.cobs_encode(body) + b"\x00" if proto < 5 else  # v5: carried
                            b"".join(p.encode(part, seq, 0, proto) for part in p.split_body(body)))
        naks = [f for f in frames(wire.module.outgoing()) if f.message.TYPE == p.MsgType.NAK]
        assert {(f.seq, f.message.reason) for f in naks} == {(seq, p.NakReason.OUT_OF_RANGE)}
    assert not received(wire.module.events(), p.SetParam)


def test_coalesced_answers_replace_the_one_still_waiting():
    wire = Wire(proto_max=2).connect()
    wire.cut = True
    for i in range(4):  # fill the window
        wire.module.send(p.Clear(f"s{i}"))
    seqs = {wire.module.send(p.Status(p.ModuleState.IDLE, frame_index=i), coalesce="status")
            for i in range(50)}
    assert len(seqs) == 1 and wire.module.queued == 1
    wire.cut = False
    wire.run(0.6)
    (status,) = received(wire.base_events, p.Status)
    assert status.frame_index == 49  # the newest content


def test_the_module_acts_on_no_command_from_a_base_that_sent_no_hello():
    module = Link(p.Role.MODULE, clock=Clock())
    module.outgoing()
    module.receive(p.encode(p.Check("kitchen"), 7))
    (nak,) = frames(module.outgoing())
    assert nak.message.TYPE == p.MsgType.NAK and nak.seq == 7
    assert nak.message.reason == p.NakReason.BAD_VERSION  # no version agreed: HELLO first
    assert not received(module.events(), p.Check)
    module.receive(p.encode(p.Hello(p.Role.BASE, 5), 1))
    module.receive(p.encode(p.Check("kitchen"), 7))  # the same seq, now accepted
    assert received(module.events(), p.Check) == [p.Check("kitchen")]


def test_ack_holdoff_counts_from_the_burst_that_answered():
    wire = Wire().connect()
    copy = p.encode(p.Pause(p.PauseCause.CHANGE_CHECK), 40, p.FLAG_URGENT, version=p.VERSION)
    wire.base.receive(copy)
    assert len(frames(wire.base.outgoing())) == p.URGENT_COPIES
    wire.clock.t += wire.base.config.ack_holdoff * 0.9
    wire.base.receive(copy)
    assert frames(wire.base.outgoing()) == []  # within the holdoff of the burst
    wire.clock.t += wire.base.config.ack_holdoff * 0.2
    wire.base.receive(copy)
    assert len(frames(wire.base.outgoing())) == p.URGENT_COPIES


def test_a_base_that_has_not_heard_the_modules_hello_reads_parts_without_failing():
    """A base restarted mid-report (or a second base on the line) is at version 1 until the
    module's HELLO reaches it, but the module already speaks 3 (it heard the base's HELLO):
    the base joins the PARTs, asks for missing ones in the PARTs' own version (NEED exists from
    version 3), and hands the message on; it never fails on them (a crash of base-sim)."""
    wire = Wire().connect()
    seq = wire.module.send(p.Fault(p.FaultCode.CAMERA_LOST, "y" * 60))
    sent: list[p.Frame] = []
    for _ in range(10):  # 50 ms of the carousel, nothing reaches the base yet
        wire.clock.t += 0.005
        wire.module.poll()
        sent += frames(wire.module.outgoing())
    fresh = Link(p.Role.BASE, clock=wire.clock, boot_id=0xCCCC)
    assert fresh.version == 1  # it has heard no HELLO of the module's
    first = [f for f in sent if f.message.index != 2]
    fresh.receive(b"".join(p.encode(f.message, f.seq, version=3) for f in first))
    fresh.outgoing()  # its first NEED, at the first PART
    wire.clock.t += fresh.config.need_interval + 0.001
    fresh.receive(p.encode(first[0].message, first[0].seq, version=3))  # a repeat
    (need,) = [f for f in frames(fresh.outgoing()) if f.message.TYPE == p.MsgType.NEED]
    assert need.seq == seq and need.message.missing == (2,) and need.version == 3
    rest = [f for f in sent if f.message.index == 2]
    fresh.receive(p.encode(rest[0].message, rest[0].seq, version=3))
    assert received(fresh.events(), p.Fault) == [p.Fault(p.FaultCode.CAMERA_LOST, "y" * 60)]
