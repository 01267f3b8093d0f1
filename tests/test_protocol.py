"""robot_change.link.protocol: COBS, CRC, every message's layout, the decoder under abuse, the
doc."""

from __future__ import annotations

import random
import re
import string
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from robot_change.errors import MessageError, ProtocolError
from robot_change.link import protocol as p

DOC = Path(__file__).resolve().parents[1] / "docs" / "protocol.md"


def raw_frame(version: int, mtype: int, seq: int = 1, flags: int = 0,
              payload: bytes = b"") -> bytes:
    """A frame with a good CRC whatever the header says (to make receivers refuse it)."""
    body = bytes((version, mtype)) + seq.to_bytes(2, "little") + bytes((flags,)) + payload
    return p.cobs_encode(body + p.crc16(body).to_bytes(2, "big")) + b"\x00"


# -- strategies: every message type ------------------------------------------------------------

u8, u16, u32 = (st.integers(0, 2**n - 1) for n in (8, 16, 32))
stations = st.text(string.ascii_letters + string.digits + "_-", min_size=1, max_size=32).filter(
    lambda s: s[0].isalnum())
texts = st.text(max_size=60).filter(lambda s: len(s.encode("utf-8", "surrogatepass")) <= 200
                                    and not any(0xD800 <= ord(c) <= 0xDFFF for c in s))
regions = st.builds(p.Region, st.sampled_from(p.RegionKind),
                    st.tuples(*[st.integers(-32768, 32767)] * 3),
                    st.tuples(*[st.integers(0, 65535)] * 3), u32)


@st.composite
def change_reports(draw):
    parts = draw(st.integers(1, 255))
    return p.ChangeReport(draw(u16), draw(st.integers(0, parts - 1)), parts, draw(stations),
                          tuple(draw(st.lists(regions, max_size=p.REGIONS_PER_PART))))


@st.composite
def param_values(draw, cls):
    param = draw(st.sampled_from(p.PARAMS))
    return cls(param.id, draw(st.integers(param.minimum, param.maximum)))


bools = st.booleans()
STRATEGIES = {
    p.Hello: st.builds(p.Hello, st.sampled_from(p.Role), u32,
                       st.text(string.printable, max_size=32), st.just(1), st.integers(1, 255)),
    p.Ack: st.just(p.Ack()),
    p.Part: st.integers(1, p.MAX_PARTS).flatmap(lambda n: st.builds(
        p.Part, st.integers(0, n - 1), st.just(n), st.binary(min_size=1, max_size=p.PART_DATA))),
    p.Need: st.builds(p.Need, st.lists(st.integers(0, p.MAX_PARTS - 1), min_size=1).map(tuple)),
    p.Nak: st.builds(p.Nak, st.sampled_from(p.NakReason), u8),
    p.Heartbeat: st.builds(p.Heartbeat, st.sampled_from(p.ModuleState), bools, bools, bools, u16,
                           u32),
    p.Pause: st.builds(p.Pause, st.sampled_from(p.PauseCause)),
    p.ChangeReport: change_reports(),
    p.Clear: st.builds(p.Clear, stations),
    p.Fault: st.builds(p.Fault, st.sampled_from(p.FaultCode), texts),
    p.Status: st.builds(p.Status, st.sampled_from(p.ModuleState), bools, bools, bools, u16, u32,
                        u32, u32, st.one_of(st.just(""), stations)),
    p.ParamValue: param_values(p.ParamValue),
    p.Captured: st.one_of(st.builds(p.Captured, stations),
                          st.builds(p.Captured, stations, u16,
                                    st.text(string.ascii_letters + "_+:", max_size=64))),
    p.CheckResult: st.builds(p.CheckResult, stations, st.sampled_from(p.CheckOutcome), u16,
                             st.tuples(*[st.integers(-32768, 32767)] * 3),
                             st.tuples(*[st.integers(-32768, 32767)] * 3),
                             st.integers(0, 1000), st.integers(0, 1000), st.integers(0, 0x3F)),
    p.BaseHeartbeat: st.builds(p.BaseHeartbeat, st.sampled_from(p.Motion)),
    p.StatusQuery: st.just(p.StatusQuery()),
    p.CaptureReference: st.builds(p.CaptureReference, stations),
    p.Check: st.builds(p.Check, stations),
    p.Watch: st.builds(p.Watch, stations),
    p.Stop: st.just(p.Stop()),
    p.Arm: st.just(p.Arm()),
    p.Disarm: st.just(p.Disarm()),
    p.Resume: st.just(p.Resume()),
    p.SetParam: param_values(p.SetParam),
    p.GetParam: st.builds(p.GetParam, st.sampled_from([q.id for q in p.PARAMS])),
}
messages = st.one_of(*STRATEGIES.values())


def test_every_message_type_has_a_class_and_a_strategy():
    assert {cls.TYPE for cls in p.MESSAGE_CLASSES} == set(p.MsgType)
    assert set(STRATEGIES) == set(p.MESSAGE_CLASSES)


@pytest.mark.parametrize("cls", p.MESSAGE_CLASSES, ids=lambda c: c.TYPE.name)
@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data(), seq=u16, flags=u8)
def test_round_trip_every_message(cls, data, seq, flags):
    message = data.draw(STRATEGIES[cls])
    wire = p.encode(message, seq, flags)
    assert wire.endswith(b"\x00") and wire.count(0) == 1
    assert len(wire) <= p.MAX_ENCODED + 1
    frame = p.FrameDecoder().feed(wire)
    assert frame == [p.Frame(message, seq, flags)]
    assert p.decode(wire) == p.Frame(message, seq, flags)


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=600))
def test_cobs_round_trip_and_no_zero(data):
    encoded = p.cobs_encode(data)
    assert 0 not in encoded
    assert p.cobs_decode(encoded) == data
    assert len(encoded) <= len(data) + 1 + len(data) // 254


@pytest.mark.parametrize("data,encoded", [
    ("00", "01 01"), ("00 00", "01 01 01"), ("11 22 00 33", "03 11 22 02 33"),
    ("11 22 33 44", "05 11 22 33 44"), ("11 00 00 00", "02 11 01 01 01"),
    (bytes(range(1, 255)).hex(), "ff " + bytes(range(1, 255)).hex()),
    (bytes(range(0, 255)).hex(), "01 ff " + bytes(range(1, 255)).hex()),
    (bytes(range(2, 256)).hex() + "00", "ff " + bytes(range(2, 256)).hex() + " 01 01"),
])
def test_cobs_reference_vectors(data, encoded):
    raw, enc = bytes.fromhex(data), bytes.fromhex(encoded)
    assert p.cobs_encode(raw) == enc
    assert p.cobs_decode(enc) == raw


def test_crc_is_ccitt_false_and_leaves_zero_over_a_whole_body():
    assert p.crc16(b"123456789") == 0x29B1
    body = p.encode_body(p.Pause(p.PauseCause.CHANGE_CHECK), 5, p.FLAG_URGENT)
    assert p.crc16(body) == 0
    assert body[-2:] == p.crc16(body[:-2]).to_bytes(2, "big")


# -- the specification's examples are the code's --------------------------------------------------


def doc_examples() -> list[dict[str, str]]:
    text = DOC.read_text(encoding="utf-8")
    blocks = re.findall(r"```hex\n(.*?)```", text, flags=re.S)
    out = []
    for block in blocks:
        fields = dict(line.split(": ", 1) for line in block.strip().splitlines())
        out.append(fields)
    return out


def test_doc_has_an_example_for_every_message_type():
    examples = doc_examples()
    assert len(examples) >= len(p.MsgType)
    named = {ex["message"].split()[0] for ex in examples}
    assert named == {t.name for t in p.MsgType}


@pytest.mark.parametrize("example", doc_examples(), ids=lambda ex: ex["message"][:40])
def test_doc_example_decodes_to_what_it_says(example):
    wire = bytes.fromhex(example["wire"])
    body = bytes.fromhex(example["body"])
    assert wire.endswith(b"\x00")
    assert p.cobs_decode(wire[:-1]) == body
    frame = p.decode(wire)
    assert isinstance(frame, p.Frame), frame
    assert p.describe(frame.message) == example["message"]
    seq, flags = re.fullmatch(r"seq=(\d+) flags=0x([0-9A-F]{2})", example["header"]).groups()
    assert (frame.seq, frame.flags) == (int(seq), int(flags, 16))
    assert p.encode(frame.message, frame.seq, frame.flags, frame.version) == wire


def test_captured_tells_what_a_station_can_see_from_version_4_only():
    plain, told = p.Captured("dock"), p.Captured("dock", 120, "xtion+measured")
    assert p.decode(p.encode(told, 3, 0, 4)).message == told
    for version in (1, 2, 3):
        assert p.decode(p.encode(plain, 3, 0, version)).message == plain
        with pytest.raises(p.MessageError, match="version 4"):
            p.encode(told, 3, 0, version)
        # an older frame with the later fields: a bad payload, answered with a NAK
        forged = raw_frame(version, p.MsgType.CAPTURED, 9, payload=told.pack())
        error = p.decode(forged)
        assert isinstance(error, p.DecodeError) and error.nak == p.NakReason.BAD_PAYLOAD
    for bad in (dict(smallest_change_mm=5), dict(noise="x"),
                dict(smallest_change_mm=70000, noise="x"), dict(smallest_change_mm=1,
                                                                  noise="n" * 65)):
        with pytest.raises(p.MessageError):
            p.Captured("dock", **bad)
    assert isinstance(p.decode(raw_frame(4, p.MsgType.CAPTURED, 9, payload=b"\x04dock\x01")),
                      p.DecodeError)


def test_doc_parameter_table_matches_the_whitelist():
    text = DOC.read_text(encoding="utf-8")
    for param in p.PARAMS:
        row = (f"| {param.id} | `{param.name}` | {param.minimum} | {param.maximum} "
               f"| {param.default} |")
        assert row in text


# -- validation on construction -------------------------------------------------------------------


@pytest.mark.parametrize("make,needle", [
    (lambda: p.Check("../etc/passwd"), "never a path"),
    (lambda: p.Check("a/b"), "never a path"),
    (lambda: p.Check(""), "station"),
    (lambda: p.Check("x" * 33), "1..32"),
    (lambda: p.Check("-lead"), "starting with"),
    (lambda: p.SetParam(1, 11), "whole number in 1..10"),
    (lambda: p.SetParam(99, 1), "unknown parameter"),
    (lambda: p.GetParam(0), "unknown parameter"),
    (lambda: p.Pause(9), "must be a PauseCause"),
    (lambda: p.Heartbeat(p.ModuleState.IDLE, fps_x10=70000), "0..65535"),
    (lambda: p.Heartbeat(p.ModuleState.IDLE, paused=2), "true or false"),
    (lambda: p.Region(1, (0, 0), (1, 1, 1), 5), "3 integers"),
    (lambda: p.Region(1, (0, 0, 40000), (1, 1, 1), 5), "-32768..32767"),
    (lambda: p.ChangeReport(1, 2, 2, "k"), "whole number in 0..1"),
    (lambda: p.ChangeReport(1, 0, 1, "k", (p.Region(1, (0, 0, 0), (1, 1, 1), 1),) * 12),
     "split_change_report"),
    (lambda: p.Fault(p.FaultCode.INTERNAL_ERROR, "x" * 201), "at most 200"),
    (lambda: p.Hello(p.Role.BASE, 1, "s" * 33), "at most 32"),
    (lambda: p.Hello(p.Role.BASE, 1, proto_min=3, proto_max=2), "proto_max"),
    (lambda: p.encode(p.Ack(), seq=70000), "seq"),
])
def test_bad_values_are_refused_on_construction(make, needle):
    with pytest.raises(MessageError, match=re.escape(needle)) as info:
        make()
    assert isinstance(info.value, ProtocolError)


def test_hello_ack_and_nak_are_read_whatever_their_version_byte():
    hello = p.Hello(p.Role.BASE, 7, "fw", 1, 9)
    for version in (1, 2, 9, 200):
        frame = p.decode(raw_frame(version, p.MsgType.HELLO, 1, payload=hello.pack()))
        assert isinstance(frame, p.Frame) and frame.message == hello and frame.version == version
    assert isinstance(p.decode(raw_frame(7, p.MsgType.ACK, 4)), p.Frame)


def test_a_version_2_message_cannot_be_sent_in_version_1():
    result = p.CheckResult("kitchen", p.CheckOutcome.NO_CHANGE)
    with pytest.raises(MessageError, match="version 2"):
        p.encode(result, 3, version=1)
    assert p.decode(p.encode(result, 3, version=2)) == p.Frame(result, 3, 0, 2)


def test_param_errors_carry_their_nak_reason():
    with pytest.raises(MessageError) as info:
        p.SetParam(1, 0)
    assert info.value.reason == p.NakReason.OUT_OF_RANGE
    with pytest.raises(MessageError) as info:
        p.SetParam(200, 0)
    assert info.value.reason == p.NakReason.UNKNOWN_PARAM


def test_messages_are_frozen():
    message = p.Check("kitchen")
    with pytest.raises(AttributeError):
        message.station = "hall"  # type: ignore[misc]


# -- each bad frame is counted under its reason --------------------------------------------------


def good(seq: int = 1) -> bytes:
    return p.encode(p.Clear("kitchen"), seq)


@pytest.mark.parametrize("bad,reason,nak", [
    (b"\x05\x01\x00", p.DecodeReason.BAD_COBS, None),
    (p.cobs_encode(b"\x01\x02\x03") + b"\x00", p.DecodeReason.TOO_SHORT, None),
    (good()[:-3] + bytes([good()[-3] ^ 0x40]) + good()[-2:], p.DecodeReason.BAD_CRC, None),
    (raw_frame(p.VERSION + 1, p.MsgType.CHECK, 7, payload=b"\x01k"), p.DecodeReason.BAD_VERSION,
     p.NakReason.BAD_VERSION),
    (raw_frame(1, p.MsgType.CHECK_RESULT, 7, payload=bytes(20) + b"\x01k"),
     p.DecodeReason.UNKNOWN_TYPE, p.NakReason.UNKNOWN_TYPE),
    (raw_frame(1, 0x7F, 7), p.DecodeReason.UNKNOWN_TYPE, p.NakReason.UNKNOWN_TYPE),
    (raw_frame(1, p.MsgType.PAUSE, 7, payload=b"\x01\x01"),
     p.DecodeReason.BAD_PAYLOAD, p.NakReason.BAD_PAYLOAD),
    (raw_frame(1, p.MsgType.PAUSE, 7, payload=b"\x09"),
     p.DecodeReason.BAD_PAYLOAD, p.NakReason.BAD_PAYLOAD),
    (raw_frame(1, p.MsgType.CHECK, 7, payload=b"\x02.."),
     p.DecodeReason.BAD_PAYLOAD, p.NakReason.BAD_PAYLOAD),
    (raw_frame(1, p.MsgType.CLEAR, 7, payload=b"\x05ab"),
     p.DecodeReason.BAD_PAYLOAD, p.NakReason.BAD_PAYLOAD),
    (raw_frame(1, p.MsgType.FAULT, 7, payload=b"\x01\x02\xff\xfe"),
     p.DecodeReason.BAD_PAYLOAD, p.NakReason.BAD_PAYLOAD),
    (raw_frame(1, p.MsgType.SET_PARAM, 7, payload=bytes([1]) + (50).to_bytes(4, "little")),
     p.DecodeReason.BAD_PAYLOAD, p.NakReason.OUT_OF_RANGE),
    (raw_frame(1, p.MsgType.GET_PARAM, 7, payload=b"\x63"),
     p.DecodeReason.BAD_PAYLOAD, p.NakReason.UNKNOWN_PARAM),
    (b"\x01" * 300 + b"\x00", p.DecodeReason.TOO_LONG, None),
    (raw_frame(1, p.MsgType.CHANGE_REPORT, 7, payload=b"\x01\x00\x02\x02\x01k\x00"),
     p.DecodeReason.BAD_PAYLOAD, p.NakReason.BAD_PAYLOAD),  # part 2 of 2
    (raw_frame(1, p.MsgType.CHANGE_REPORT, 7, payload=b"\x01\x00\x00\x00\x01k\x00"),
     p.DecodeReason.BAD_PAYLOAD, p.NakReason.BAD_PAYLOAD),  # 0 parts
    (raw_frame(1, p.MsgType.CHANGE_REPORT, 7, payload=b"\x01\x00\x00\x01\x01k\x0c"
               + p.Region(1, (0, 0, 0), (1, 1, 1), 1).pack() * 12),
     p.DecodeReason.BAD_PAYLOAD, p.NakReason.BAD_PAYLOAD),  # 12 regions in a part
    (raw_frame(1, p.MsgType.CHANGE_REPORT, 7, payload=b"\x01\x00\x00\x01\x01k\x01"
               + b"\x03" + bytes(16)),
     p.DecodeReason.BAD_PAYLOAD, p.NakReason.BAD_PAYLOAD),  # region kind 3
    (raw_frame(1, p.MsgType.CHANGE_REPORT, 7, payload=b"\x01\x00\x00\x01\x01k\x01"
               + bytes(17)[:-1]),
     p.DecodeReason.BAD_PAYLOAD, p.NakReason.BAD_PAYLOAD),  # region cut short
])
def test_bad_frame_is_counted_then_the_next_frame_decodes(bad, reason, nak):
    decoder = p.FrameDecoder()
    out = decoder.feed(bad + good(2))
    assert len(out) == 2
    error, frame = out
    assert isinstance(error, p.DecodeError) and error.reason == reason, error
    assert error.nak == nak
    if nak is not None:
        assert error.seq == 7
    assert frame == p.Frame(p.Clear("kitchen"), 2, 0)
    assert decoder.counts[reason] == 1 and decoder.errors == 1 and decoder.frames == 1


def test_oversized_stream_without_delimiter_is_counted_once_and_memory_stays_bounded():
    decoder = p.FrameDecoder()
    out = []
    for _ in range(100):  # 10 kB of non-zero bytes, fed in small pieces
        out += decoder.feed(b"\x55" * 100)
        assert len(decoder._buf) <= p.MAX_ENCODED
    out += decoder.feed(b"\x00" + good(3))
    assert [type(x) for x in out] == [p.DecodeError, p.Frame]
    assert decoder.counts[p.DecodeReason.TOO_LONG] == 1
    assert out[-1].seq == 3


def test_empty_frames_are_ignored_not_counted():
    decoder = p.FrameDecoder()
    assert decoder.feed(b"\x00\x00\x00" + good() + b"\x00\x00") == [p.Frame(p.Clear("kitchen"), 1)]
    assert decoder.errors == 0


def test_frames_split_across_feeds_decode():
    wire = b"".join(p.encode(p.Heartbeat(p.ModuleState.WATCHING, frame_index=i)) for i in range(50))
    decoder = p.FrameDecoder()
    rng = random.Random(3)
    out, i = [], 0
    while i < len(wire):
        n = rng.randint(1, 23)
        out += decoder.feed(wire[i:i + n])
        i += n
    assert [f.message.frame_index for f in out] == list(range(50))


# -- fuzz -------------------------------------------------------------------------------------


@settings(max_examples=300, deadline=None)
@given(garbage=st.binary(max_size=700))
def test_random_bytes_never_crash_and_resync_on_the_next_frame(garbage):
    decoder = p.FrameDecoder()
    out = decoder.feed(garbage)
    assert all(isinstance(x, (p.Frame, p.DecodeError)) for x in out)
    out = decoder.feed(b"\x00" + good(11) + good(12))
    assert [x.seq for x in out if isinstance(x, p.Frame)][-2:] == [11, 12]
    bad = sum(isinstance(x, p.DecodeError) for x in decoder.feed(b""))
    assert decoder.errors >= bad


@settings(max_examples=150, deadline=None)
@given(message=messages, cut=st.integers(1, 400))
def test_truncated_frames_are_errors_never_messages(message, cut):
    wire = p.encode(message, 9)
    cut = 1 + cut % (len(wire) - 2)  # keep at least one byte, drop at least one before the 0x00
    decoder = p.FrameDecoder()
    out = decoder.feed(wire[:cut] + b"\x00" + good(10))
    assert all(isinstance(x, p.DecodeError) for x in out[:-1])
    assert out[-1] == p.Frame(p.Clear("kitchen"), 10)
    assert decoder.errors == len(out) - 1 >= 1


@settings(max_examples=300, deadline=None)
@given(message=messages, data=st.data())
def test_any_single_bit_flip_is_caught(message, data):
    wire = bytearray(p.encode(message, 21))
    index = data.draw(st.integers(0, len(wire) - 2))  # never the delimiter itself
    wire[index] ^= 1 << data.draw(st.integers(0, 7))
    decoder = p.FrameDecoder()
    out = decoder.feed(bytes(wire) + good(22))
    assert out[-1] == p.Frame(p.Clear("kitchen"), 22)
    assert out[:-1] and all(isinstance(x, p.DecodeError) for x in out[:-1])
    assert decoder.errors == len(out) - 1


def test_a_flood_of_frames_with_noise_between_is_all_accounted_for():
    rng = random.Random(5)
    wire, good_count, bad_count = bytearray(), 0, 0
    for i in range(3000):
        if rng.random() < 0.2:
            chunk = bytes(rng.randrange(1, 256) for _ in range(rng.randint(1, 40)))
            wire += chunk + b"\x00"
            bad_count += 1
        wire += p.encode(p.Heartbeat(p.ModuleState.WATCHING, frame_index=i))
        good_count += 1
    decoder = p.FrameDecoder()
    frames = [x for x in decoder.feed(bytes(wire)) if isinstance(x, p.Frame)]
    assert len(frames) == decoder.frames == good_count
    assert decoder.errors == bad_count  # every noise burst counted, under some reason


# -- long reports ----------------------------------------------------------------------------


def region(i: int) -> p.Region:
    return p.Region(p.RegionKind.APPEARED if i % 2 else p.RegionKind.DISAPPEARED,
                    (i, -i, 1000 + i), (10 + i, 20, 30), 100 + i)


def test_long_report_splits_and_joins_in_any_order_with_duplicates():
    regions = [region(i) for i in range(30)]
    parts = p.split_change_report(4, "kitchen", regions)
    assert [len(x.regions) for x in parts] == [11, 11, 8]
    assert all(len(p.encode(x, 1)) <= p.MAX_ENCODED + 1 for x in parts)
    assembler = p.ReportAssembler()
    arrivals = [parts[2], parts[0], parts[2], parts[1]]
    results = [assembler.add(x) for x in arrivals]
    assert results[:3] == [None, None, None]
    assert results[3] == p.AssembledReport(4, "kitchen", tuple(regions))


def test_empty_report_is_one_part_and_assembler_memory_is_bounded():
    (only,) = p.split_change_report(1, "dock", [])
    assert (only.part, only.parts, only.regions) == (0, 1, ())
    assembler = p.ReportAssembler(max_pending=2)
    for rid in range(5):
        assert assembler.add(p.split_change_report(rid, "k", [region(i) for i in range(20)])[0]) \
            is None
    assert len(assembler._pending) == 2 and assembler.dropped == 3
    with pytest.raises(MessageError, match="at most 255"):
        p.split_change_report(1, "k", [region(0)] * (256 * p.REGIONS_PER_PART))
