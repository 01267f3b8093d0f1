"""Protocol version 5 (issue 46): the base's commands carried in PARTs as the module's are, a
HELLO that gets through noise, and a lost ACK that is not a link fault.  Stepped with the fake
clock and the in-memory line of tests/test_link.py."""

from __future__ import annotations

import io
import json

import pytest

from robot_change.link import protocol as p
from robot_change.link.session import Delivered, Link, LinkState, SendFailed, StateChanged
from robot_change.tools.linkbench import run_link_bench
from tests.test_link import Wire, frames, received
from tests.test_protocol import raw_frame


def faults(events) -> int:
    return sum(isinstance(e, StateChanged) and e.new == LinkState.FAULTY for e in events)


def test_version_5_carries_the_bases_commands_in_parts_joined_by_the_module():
    wire = Wire().connect()
    assert wire.base.version == wire.module.version == 5
    seq = wire.base.send(p.Check("kitchen"))
    wire.base.poll()
    out = frames(wire.base.outgoing())
    parts = [f for f in out if f.message.TYPE == p.MsgType.PART]
    assert parts and all(f.seq == seq and f.version == 5 for f in parts)
    assert max(len(p.encode(f.message, f.seq, version=5)) for f in parts) <= 19
    wire.module.receive(b"".join(p.encode(f.message, f.seq, version=5) for f in out))
    acks = [f for f in frames(wire.module.outgoing()) if f.message.TYPE == p.MsgType.ACK]
    assert len(acks) == p.URGENT_COPIES and {f.seq for f in acks} == {seq}  # a burst
    assert received(wire.module.events(), p.Check) == [p.Check("kitchen")]
    wire.run(0.3)
    assert [e.seq for e in wire.base_events if isinstance(e, Delivered)] == [seq]


def test_the_module_needs_what_is_missing_of_a_bases_command():
    wire = Wire().connect()
    seq = wire.base.send(p.CaptureReference("station-with-a-long-name-0123456"))
    parts = []
    for _ in range(5):
        wire.clock.t += 0.005
        wire.base.poll()
        parts += [f for f in frames(wire.base.outgoing()) if f.message.TYPE == p.MsgType.PART]
    assert parts[0].message.count == 5
    wire.module.receive(p.encode(parts[0].message, seq, version=5))
    (need,) = [f for f in frames(wire.module.outgoing()) if f.message.TYPE == p.MsgType.NEED]
    assert need.seq == seq and need.version == 5
    assert need.message.missing == tuple(range(1, parts[0].message.count))
    wire.base.receive(p.encode(p.Need((2,)), seq, version=5))
    again = []
    for _ in range(5):
        wire.clock.t += 0.005
        wire.base.poll()
        again += frames(wire.base.outgoing())
    assert {f.message.index for f in again if f.message.TYPE == p.MsgType.PART} == {2}


@pytest.mark.parametrize("proto", [4, 5])
def test_a_bases_part_or_need_is_a_wrong_direction_before_version_5(proto):
    module = Link(p.Role.MODULE)
    module.receive(p.encode(p.Hello(p.Role.BASE, 5, proto_max=proto), 1))
    module.outgoing()
    module.receive(raw_frame(proto, p.MsgType.PART, 9, payload=b"\x00\x02\x05\x43\x09"))
    naks = [f for f in frames(module.outgoing()) if f.message.TYPE == p.MsgType.NAK]
    if proto < 5:
        assert [f.message.reason for f in naks] == [p.NakReason.WRONG_DIRECTION]
    else:
        assert not naks  # a piece of a command being joined


def test_a_module_message_carried_by_the_base_is_a_wrong_direction_once_joined():
    """A PAUSE is the module's to send: a whole one from the base is answered NAK
    WRONG_DIRECTION (section 6), and so is one the base carries in PARTs, once joined (it was
    dropped in silence, and the base carried it for CARRY_TIMEOUT); the module acts on
    neither."""
    module = Link(p.Role.MODULE)
    module.receive(p.encode(p.Hello(p.Role.BASE, 5), 1))
    module.outgoing()
    body = p.encode_body(p.Pause(p.PauseCause.CHANGE_CHECK), 9, 0, 5)
    module.receive(b"".join(p.encode(part, 9, 0, 5) for part in p.split_body(body)))
    naks = [f for f in frames(module.outgoing()) if f.message.TYPE == p.MsgType.NAK]
    assert [(f.seq, f.message.reason, f.message.refused_type) for f in naks] == [
        (9, p.NakReason.WRONG_DIRECTION, p.MsgType.PAUSE)]
    assert not received(module.events(), p.Pause)


def test_a_hello_whose_versions_do_not_meet_is_naked_in_version_1():
    """The NAK of an incompatible HELLO carries the HELLO's version byte (1), not the last
    session's (a restarted base offering 6..7 got NAKs of version 5)."""
    module = Link(p.Role.MODULE)
    module.receive(p.encode(p.Hello(p.Role.BASE, 5), 1))
    assert module.version == 5
    module.outgoing()
    module.receive(p.encode(p.Hello(p.Role.BASE, 6, proto_min=6, proto_max=7), 1,
                            version=1))  # as every HELLO is sent
    naks = [f for f in frames(module.outgoing()) if f.message.TYPE == p.MsgType.NAK]
    assert naks and all(f.version == 1 and f.message.reason == p.NakReason.BAD_VERSION
                        for f in naks)
    assert module.state == LinkState.INCOMPATIBLE


def test_a_malformed_hello_is_naked_bad_payload_in_version_1():
    """A HELLO offering 5..3 was NAKed OUT_OF_RANGE (SET_PARAM's reason, 7.3) in the session's
    version 5, where 7.5 says a HELLO's NAK carries the HELLO's version byte, 1."""
    module = Link(p.Role.MODULE)
    module.receive(p.encode(p.Hello(p.Role.BASE, 5), 1))
    assert module.version == 5
    module.outgoing()
    # versions 5..3, role 2 (the base), boot id 6, no software text
    module.receive(raw_frame(1, p.MsgType.HELLO, 2, 0, bytes((5, 3, 2)) + (6).to_bytes(4, "little")
                             + b"\x00"))
    naks = [f for f in frames(module.outgoing()) if f.message.TYPE == p.MsgType.NAK]
    assert [(f.version, f.seq, f.message.reason) for f in naks] == [
        (1, 2, p.NakReason.BAD_PAYLOAD)]


@pytest.mark.parametrize("proto", [4, 5])
def test_the_bases_commands_through_10_percent_byte_corruption(proto):
    """Issue 46 item 1: at 10 % (flipped bytes) every CHECK reaches the module once and the
    base never declares the link faulty; version 4 (whole frames) lost a third of them."""
    wire = Wire(seed=3, proto_max=proto).connect()
    wire.noise = 0.10
    seqs = []
    for i in range(20):
        seqs.append(wire.base.send(p.Check(f"s{i}")))
        wire.run(0.6, dt=0.005)
        if wire.base.in_flight:
            wire.run(wire.base.config.carry_timeout, dt=0.02)
    got = [m.station for m in received(wire.module_events, p.Check)]
    if proto == 5:
        assert got == [f"s{i}" for i in range(20)]  # each once, in order
        assert faults(wire.base_events) == 0
        assert not [e for e in wire.base_events if isinstance(e, SendFailed)]
    else:
        assert len(got) < 20 or faults(wire.base_events) > 0


def test_commands_sent_back_to_back_are_joined_in_the_order_sent():
    """A capture then a check: the shorter would be joined first if both were carried at
    once; the base carries one at a time."""
    wire = Wire().connect()
    wire.base.send(p.CaptureReference("a-rather-long-station-name"))
    wire.base.send(p.Check("b"))
    wire.run(0.5)
    assert [type(m) for m in received(wire.module_events)
            if not isinstance(m, p.BaseHeartbeat)] == [p.CaptureReference, p.Check]


def test_hello_goes_out_as_a_short_urgent_burst_answered_by_an_ack_burst():
    link = Link(p.Role.MODULE)
    link.poll()
    hellos = [f for f in frames(link.outgoing()) if f.message.TYPE == p.MsgType.HELLO]
    assert len(hellos) == p.URGENT_COPIES
    assert all(f.flags == p.FLAG_URGENT and f.version == 1 and f.message.software == ""
               for f in hellos)
    assert len(p.encode(hellos[0].message, 1, p.FLAG_URGENT, 1)) <= 18
    base = Link(p.Role.BASE)
    base.outgoing()
    base.receive(b"".join(p.encode(f.message, f.seq, f.flags, 1) for f in hellos))
    acks = [f for f in frames(base.outgoing()) if f.message.TYPE == p.MsgType.ACK]
    assert len(acks) == p.URGENT_COPIES


def test_a_restarted_module_is_seen_through_10_percent_corruption_within_a_second():
    """Issue 46 item 2: its HELLO (a burst of 17-byte frames) reaches the base, 20 restarts."""
    wire = Wire(seed=5).connect()
    wire.noise = 0.10
    for k in range(20):
        wire.module = Link(p.Role.MODULE, clock=wire.clock, boot_id=0xC000 + k)
        wire.base_events.clear()
        started = wire.clock.t
        while not [h for h in received(wire.base_events, p.Hello) if h.boot_id == 0xC000 + k]:
            wire.step(0.005)
            assert wire.clock.t - started < 1.0, k
        wire.run(0.5, dt=0.005)


def test_a_message_the_peer_never_acks_fails_without_faulting_a_link_the_peer_hears():
    """Version 5: a whole frame is tried for CARRY_TIMEOUT; when it fails while the peer
    acknowledges our other messages, only the message has failed."""
    wire = Wire().connect()
    lost = wire.base.send(p.Resume())  # urgent: whole frames; every copy of it is lost
    for _ in range(int(wire.base.config.carry_timeout / 0.05) + 10):
        wire.clock.t += 0.05
        wire.base.poll()
        wire.module.poll()
        if wire.base.queued == 0 and wire.base.in_flight <= 1:
            wire.base.send(p.StatusQuery())  # these get through and are acknowledged
        out = wire.base.outgoing()
        kept = b"".join(p.encode(f.message, f.seq, f.flags, f.version) for f in frames(out)
                        if f.seq != lost)
        wire.module.receive(kept)
        wire.base.receive(wire.module.outgoing())
        wire.base_events += wire.base.events()
    (failed,) = [e for e in wire.base_events if isinstance(e, SendFailed)]
    assert failed.seq == lost and "100 tries" in failed.reason
    assert wire.base.state == LinkState.UP and faults(wire.base_events) == 0


def test_a_peer_that_hears_nothing_of_ours_is_a_link_fault_after_the_carry_timeout():
    wire = Wire().connect()
    wire.base.send(p.Check("kitchen"))
    for _ in range(int(wire.base.config.carry_timeout / 0.05) + 10):
        wire.clock.t += 0.05
        wire.base.poll()
        wire.module.poll()
        wire.base.outgoing()  # the module is deaf; it still talks
        wire.base.receive(wire.module.outgoing())
        wire.base_events += wire.base.events()
    assert [e for e in wire.base_events if isinstance(e, SendFailed)]
    assert faults(wire.base_events) >= 1


@pytest.mark.parametrize("proto", [4, 5])
def test_an_idle_link_through_10_percent_corruption_is_not_declared_faulty(proto):
    """Heartbeats alone (17 bytes: 15 % get through): in version 4 a second without an intact
    one is a link fault; in version 5 a damaged frame is a peer talking, not a silent one."""
    wire = Wire(seed=11, proto_max=proto).connect()
    wire.module.set_heartbeat(p.Heartbeat(p.ModuleState.IDLE))
    wire.base.set_heartbeat(p.BaseHeartbeat(p.Motion.PARKED))
    wire.noise = 0.10
    wire.run(60.0, dt=0.01)
    if proto == 5:
        assert faults(wire.base_events) == faults(wire.module_events) == 0
    else:
        assert faults(wire.base_events) > 0


def test_a_silent_peer_is_still_a_link_fault_in_version_5():
    wire = Wire().connect()
    wire.module.set_heartbeat(p.Heartbeat(p.ModuleState.IDLE))
    wire.run(0.5)
    wire.cut = True
    wire.run(wire.base.config.silence_timeout + 0.2)
    assert wire.base.state == wire.module.state == LinkState.FAULTY


@pytest.mark.parametrize("mode,key", [("check", "answered"), ("restart", "seen"), ("idle", None)])
def test_link_bench_measures_both_directions_over_a_real_pty_pair(mode, key):
    out = io.StringIO()
    result = run_link_bench(0.02, 3, json=True, seed=1, out=out, mode=mode)
    assert json.loads(out.getvalue()) == result and result["proto"] == p.VERSION
    if key is not None:
        assert result[key] == 3 and result[f"{'answer' if key == 'answered' else key}_p99_ms"]
    assert result["link_faults"] == result["base_link_faults"] == 0
