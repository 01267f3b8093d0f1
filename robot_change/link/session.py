"""The session over a byte port: sequence numbers, acks, retries, duplicates, heartbeats.

:class:`Link` is a state machine without threads or I/O: feed it received bytes with
:meth:`Link.receive`, let time pass with :meth:`Link.poll`, take the bytes to write from
:meth:`Link.outgoing` and what happened from :meth:`Link.events`.  Time comes from an injectable
``clock`` (or the ``now`` argument), so tests step it deterministically.  :class:`LinkRunner`
pumps a Link over a real port (pyserial object or anything with ``read``/``write``).

The rules (docs/protocol.md, "Session"): every sequenced message is acknowledged by seq; the
sender retries every 100 ms, 5 tries in all (version 5: for CARRY_TIMEOUT), then fails the
message and declares the link FAULTY (version 5: only when the peer acknowledged nothing of ours
meanwhile); the receiver acks duplicates again but delivers them once; urgent messages (PAUSE,
RESUME, HELLO) and their ACKs go out as bursts of URGENT_COPIES; from version 3 the module's
other messages, from version 5 the base's too, are carried in PARTs; heartbeats flow both ways
whatever the state.

:class:`LinkConfig`, :class:`LinkState`, the events and :class:`LinkStats` are in
:mod:`robot_change.link.session_types`, :class:`LinkRunner` in
:mod:`robot_change.link.runner`; all are re-exported here.
"""

from __future__ import annotations

import random
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from robot_change.errors import LinkError
from robot_change.link.protocol import (
    FLAG_RETRY,
    FLAG_URGENT,
    FROZEN_TYPES,
    MIN_VERSION,
    VERSION,
    Ack,
    BaseHeartbeat,
    DecodeError,
    Frame,
    FrameDecoder,
    Heartbeat,
    Hello,
    Message,
    MsgType,
    Nak,
    NakReason,
    Need,
    Part,
    Role,
    decode_body,
    encode,
    encode_body,
    may_send,
    split_body,
)
from robot_change.link.runner import LinkRunner
from robot_change.link.session_types import (
    Delivered,
    Event,
    LinkConfig,
    LinkState,
    LinkStats,
    PortProblem,
    Received,
    SendFailed,
    StateChanged,
)

__all__ = [
    "Delivered", "Event", "Link", "LinkConfig", "LinkRunner", "LinkState", "LinkStats",
    "PortProblem", "Received", "SendFailed", "StateChanged",
]


@dataclass
class _Pending:
    seq: int
    message: Message
    urgent: bool
    tries: int = 0
    first_at: float = 0.0
    next_at: float = 0.0
    #: version 3: the encoded PART frames carrying the message, the indices still to send
    #: (from the base's last NEED; all at first) and the next one's position in them.
    parts: list[bytes] | None = None
    wanted: list[int] | None = None
    cursor: int = 0
    coalesce: Any = None


@dataclass
class _Assembly:
    count: int
    got: dict[int, bytes]
    started: float
    need_at: float = -1.0


_HEARTBEAT_OF = {Role.MODULE: Heartbeat, Role.BASE: BaseHeartbeat}


class Link:
    """One end of the module <-> base session (``role`` says which end), sans-IO.

    ``clock`` is a callable returning seconds (monotonic); every method that takes ``now`` uses
    ``clock()`` when it is None.  ``proto_max``: the highest protocol version this end offers
    (an older peer is simulated with 1); :attr:`version` is the one the two ends agreed on.
    ``software``: HELLO's informational field, empty by default (docs/protocol.md 7.5: every
    byte of a HELLO costs it some of its chance through a noisy line).
    """

    def __init__(self, role: Role, *, clock: Callable[[], float] = time.monotonic,
                 config: LinkConfig | None = None, boot_id: int | None = None,
                 software: str = "", proto_max: int = VERSION,
                 admit: Callable[[Message], NakReason | None] | None = None) -> None:
        if not MIN_VERSION <= proto_max <= VERSION:
            raise LinkError(f"proto_max {proto_max}: this code speaks {MIN_VERSION}..{VERSION}")
        self.proto_max = proto_max
        #: The session's protocol version: the highest both ends speak, MIN_VERSION until the
        #: peer's HELLO has been heard.
        self.version = MIN_VERSION
        self.role = Role(role)
        self.peer_role = Role.BASE if self.role == Role.MODULE else Role.MODULE
        self.clock = clock
        self.config = config or LinkConfig()
        self.boot_id = random.getrandbits(32) if boot_id is None else boot_id
        self.software = software
        #: Called with every new sequenced message from the peer before it is acknowledged; a
        #: NakReason refuses it (NAK, not remembered as received), None accepts it.
        self.admit = admit
        self.decoder = FrameDecoder()
        self.stats = LinkStats()
        self.state = LinkState.CONNECTING
        self.peer: Hello | None = None
        self._next_seq = 1
        self._urgent_q: deque[_Pending] = deque()
        self._normal_q: deque[_Pending] = deque()
        self._inflight: dict[int, _Pending] = {}
        self._hello_seq: int | None = None
        self._greeted = False
        # seqs of the peer's current boot this end answered (docs/protocol.md 7.2), oldest
        # first: None when acknowledged, else the NAK (reason, type) that refused it
        self._seen: dict[int, tuple[NakReason, int] | None] = {}
        self._ack_burst_at: dict[int, float] = {}
        self._out = bytearray()
        self._events: list[Event] = []
        self._heartbeat: Message | None = None
        self._next_heartbeat = 0.0
        self._assemblies: dict[int, _Assembly] = {}
        self._part_credit = 0.0
        self._part_clock: float | None = None
        self._carousel = 0
        now = clock()
        self._last_rx = now
        #: the last frame from the peer, intact or not (version 5's silence rule, 7.7)
        self._last_frame = now
        self._last_ack = -float("inf")
        self._next_hello = now

    # -- the application's side ---------------------------------------------------------------

    def send(self, message: Message, now: float | None = None, *, coalesce: Any = None) -> int:
        """Queue a sequenced message; return its seq.  Urgent ones go out at once, ahead of all.

        ``coalesce``: a key (e.g. "status"); when a message sent with the same key still waits
        in the queue (not yet transmitted), it is replaced by this one, which takes its seq
        and place: a flood of queries is answered by one up-to-date answer waiting at most."""
        if not isinstance(message, Message):
            raise LinkError(f"send() wants a protocol message, got {type(message).__name__}")
        name = message.TYPE.name
        if isinstance(message, Hello) or not message.SEQUENCED:
            hint = "use set_heartbeat()" if "HEARTBEAT" in name else "the link sends it itself"
            raise LinkError(f"{name} is not sent with send(): {hint}")
        if not may_send(self.role, type(message)):
            raise LinkError(f"{name} is sent by the {message.SENDER.name.lower()}, "  # type: ignore[union-attr]
                            f"not by the {self.role.name.lower()}")
        if message.since() > self.version:
            raise LinkError(f"{name} needs protocol version {message.since()}; this session "
                            f"speaks {self.version} (check link.version first)")
        if coalesce is not None and not message.URGENT:
            for waiting in self._normal_q:
                if waiting.coalesce == coalesce:
                    waiting.message = message
                    return waiting.seq
        pending = _Pending(self._take_seq(), message, message.URGENT, coalesce=coalesce)
        queue = self._urgent_q if pending.urgent else self._normal_q
        queue.append(pending)
        if len(queue) > self.config.max_queue:
            dropped = queue.popleft()
            self._fail(dropped, f"send queue full ({self.config.max_queue} messages): the link is "
                       f"{self.state.value}; check the cable and that the base is running")
        self._promote(self._now(now))
        return pending.seq

    def set_heartbeat(self, message: Message, now: float | None = None) -> None:
        """Install the heartbeat repeated every heartbeat_interval; a changed one goes out at
        once."""
        expected = _HEARTBEAT_OF[self.role]
        if type(message) is not expected:
            raise LinkError(f"the {self.role.name.lower()} sends {expected.TYPE.name}, "
                            f"not {type(message).__name__}")
        if message != self._heartbeat:
            self._next_heartbeat = self._now(now)
        self._heartbeat = message

    def events(self) -> list[Event]:
        """What happened since the last call (and forget it)."""
        events, self._events = self._events, []
        return events

    def outgoing(self) -> bytes:
        """The bytes to write to the port now (and forget them)."""
        data = bytes(self._out)
        self._out.clear()
        self.stats.bytes_out += len(data)
        return data

    @property
    def last_heard(self) -> float:
        """Clock time of the last valid frame from the peer (link creation time before any)."""
        return self._last_rx

    @property
    def in_flight(self) -> int:
        """Sequenced messages sent and not yet acknowledged (HELLO included)."""
        return len(self._inflight)

    @property
    def queued(self) -> int:
        """Sequenced messages waiting for the window (or for the first HELLO to be acked)."""
        return len(self._urgent_q) + len(self._normal_q)

    def next_deadline(self) -> float:
        """When :meth:`poll` next has something to do (clock seconds)."""
        times = [p.next_at for p in self._inflight.values()]
        if any(p.parts is not None for p in self._inflight.values()):
            times.append((self._part_clock or 0.0) + 0.002)  # the PART carousel runs
        if self._heartbeat is not None and self.state != LinkState.INCOMPATIBLE:
            times.append(self._next_heartbeat)
        if self.state == LinkState.UP:
            times.append(self._heard_at() + self.config.silence_timeout)
        elif self._hello_seq is None and self.state != LinkState.INCOMPATIBLE:
            times.append(self._next_hello)
        return min(times, default=float("inf"))

    def counters(self) -> dict[str, Any]:
        """Every counter, decode errors by reason included, as a flat dict."""
        out: dict[str, Any] = dict(vars(self.stats))
        out["frames_good"] = self.decoder.frames
        out.update({f"decode_{reason.value}": n for reason, n in self.decoder.counts.items()})
        return out

    # -- time -----------------------------------------------------------------------------------

    def poll(self, now: float | None = None) -> None:
        """Run the timers: HELLO probes, queued messages, retries, heartbeats, peer silence."""
        now = self._now(now)
        cfg = self.config
        if (self.state in (LinkState.CONNECTING, LinkState.FAULTY) and self._hello_seq is None
                and now >= self._next_hello):
            self._start_hello(now)
        self._promote(now)
        for pending in [p for p in self._inflight.values() if p.next_at <= now]:
            if pending.tries >= self._tries_allowed(pending) or pending.parts is not None:
                self._give_up(pending, now)
            else:
                self._transmit(pending, now)
        self._run_carousel(now)
        if (self._heartbeat is not None and now >= self._next_heartbeat
                and self.state != LinkState.INCOMPATIBLE):  # in no version the peer reads
            self._out += encode(self._heartbeat, version=self.version)
            self.stats.heartbeats_sent += 1
            self._next_heartbeat = now + cfg.heartbeat_interval
        if self.state == LinkState.UP and now - self._heard_at() > cfg.silence_timeout:
            self._set_state(LinkState.FAULTY,
                            f"nothing heard from the {self.peer_role.name.lower()} "
                            f"for {now - self._heard_at():.2f} s: check the cable and that it is "
                            "powered", now)

    # -- bytes in ------------------------------------------------------------------------------

    def receive(self, data: bytes, now: float | None = None) -> None:
        """Consume bytes read from the port: ack, NAK, deliver, as the protocol says."""
        now = self._now(now)
        self.stats.bytes_in += len(data)
        for item in self.decoder.feed(data):
            self._last_frame = now
            if type(item) is DecodeError:
                # never NAK an ACK or a NAK, nor a NEED: its seq is the module's own message's,
                # and a NAK of it would fail an unrelated message of the base with that seq
                if item.nak is not None and item.msg_type not in (MsgType.ACK, MsgType.NAK,
                                                                  MsgType.NEED):
                    self._refuse(item.seq or 0, item.nak, item.msg_type or 0)
                continue
            self._on_frame(item, now)  # type: ignore[arg-type]

    def _on_frame(self, frame: Frame, now: float) -> None:
        self._last_rx = now
        self.stats.frames_in += 1
        message, seq = frame.message, frame.seq
        kind = message.TYPE
        if frame.version > self.proto_max and kind not in FROZEN_TYPES:
            if message.SEQUENCED:  # an end limited to older versions reads them as bad
                self._nak(seq, NakReason.BAD_VERSION, kind)
            return
        if kind == MsgType.ACK:
            self._on_ack(seq, now)
        elif kind == MsgType.NAK:
            self._on_nak(seq, message)  # type: ignore[arg-type]
        elif not may_send(self.peer_role, type(message), frame.version) or (
                isinstance(message, Hello) and message.role != self.peer_role):
            self._refuse(seq, NakReason.WRONG_DIRECTION, kind)
        elif kind == MsgType.PART:
            self._on_part(frame, now)
        elif kind == MsgType.NEED:
            self._on_need(seq, message)  # type: ignore[arg-type]
        elif not message.SEQUENCED:
            self.stats.heartbeats_received += 1
            self._events.append(Received(message, seq))
        else:
            self._on_sequenced(frame, now)

    def _on_sequenced(self, frame: Frame, now: float) -> None:
        message, seq = frame.message, frame.seq
        new_peer = isinstance(message, Hello) and (self.peer is None or
                                                   message.boot_id != self.peer.boot_id)
        if new_peer:  # the peer (re)started: its sequence numbers start afresh
            self._seen.clear()
            self._ack_burst_at.clear()
            self._assemblies.clear()  # half-joined messages of the old boot
        if isinstance(message, Hello) and not self._meets(message):
            # docs/protocol.md 7.5: NAKed, not acknowledged, so that the peer learns it too
            self.peer = message
            self._nak(seq, NakReason.BAD_VERSION, message.TYPE, min(frame.version, self.proto_max))
            self._set_state(LinkState.INCOMPATIBLE, f"the {self.peer_role.name.lower()} speaks "
                            f"protocol {message.proto_min}..{message.proto_max}, this end "
                            f"{MIN_VERSION}..{self.proto_max}: update the older side", now)
            return
        if seq in self._seen:
            refused = self._seen[seq]
            if refused is not None:  # a copy sent before our NAK arrived: the same answer
                self._nak(seq, *refused)
            elif self._ack(frame, now):  # copies of one burst are one transmission
                self.stats.duplicates += 1
            return
        if self.role == Role.MODULE and self.peer is None and not isinstance(message, Hello):
            # docs/protocol.md 7.5: no command is acted on before the base's HELLO (no version
            # agreed, its duplicate memory not cleared): refused, not remembered
            self._nak(seq, NakReason.BAD_VERSION, message.TYPE)
            self.stats.before_hello += 1
            return
        if self.admit is not None and not isinstance(message, Hello):
            refusal = self.admit(message)
            if refusal is not None:
                self._refuse(seq, refusal, message.TYPE)
                return
        self._ack(frame, now)
        self._remember(seq, None)
        if isinstance(message, Hello):
            self._on_hello(message, new_peer, now)
        self._events.append(Received(message, seq))

    def _on_part(self, frame: Frame, now: float) -> None:
        """Version 3: one PART of a carried message; join, NEED what is missing, and hand the
        whole message on as if it had arrived in one frame (its ACK goes out as a burst)."""
        part: Part = frame.message  # type: ignore[assignment]
        seq = frame.seq
        self.stats.parts_received += 1
        if seq in self._seen:  # joined already: our answer was lost; another one
            refused = self._seen[seq]
            if refused is not None:
                self._nak(seq, *refused)
            else:
                self._ack(Frame(part, seq, FLAG_URGENT, frame.version), now)
            return
        assembly = self._assemblies.get(seq)
        if assembly is None or assembly.count != part.count:
            assembly = self._assemblies[seq] = _Assembly(part.count, {}, now)
            while len(self._assemblies) > self.config.max_assemblies:
                del self._assemblies[next(iter(self._assemblies))]
                self.stats.assemblies_dropped += 1
        assembly.got[part.index] = part.data
        if len(assembly.got) < assembly.count:
            if now - assembly.need_at >= self.config.need_interval:
                assembly.need_at = now
                missing = tuple(i for i in range(assembly.count) if i not in assembly.got)
                # in the PART's version, as an ACK answers in its frame's (7.5): an end that
                # has not heard the peer's HELLO yet is still at version 1, where NEED is not
                self._out += encode(Need(missing), seq, version=frame.version)
                self.stats.needs_sent += 1
            return
        del self._assemblies[seq]
        inner = decode_body(b"".join(assembly.got[i] for i in range(assembly.count)))
        if type(inner) is DecodeError and inner.nak is not None and inner.seq == seq:
            self._refuse(seq, inner.nak, inner.msg_type or 0)  # intact, but not acceptable
            return
        if (type(inner) is Frame and inner.seq == seq and inner.message.SEQUENCED
                and not may_send(self.peer_role, type(inner.message), inner.version)):
            # intact, its own CRC good, but not the peer's to send: told, as a whole frame is
            # (section 6), or the peer would carry it until CARRY_TIMEOUT
            self._refuse(seq, NakReason.WRONG_DIRECTION, inner.message.TYPE)
            return
        if (type(inner) is not Frame or inner.seq != seq or not inner.message.SEQUENCED
                or inner.message.URGENT or isinstance(inner.message, Hello)
                or not may_send(self.peer_role, type(inner.message), inner.version)):
            self.stats.carried_bad += 1  # a part with a falsely matching CRC: start again
            return
        self.stats.carried += 1
        self._on_sequenced(Frame(inner.message, seq, inner.flags | FLAG_URGENT, inner.version), now)

    def _on_need(self, seq: int, need: Need) -> None:
        self.stats.needs_received += 1
        pending = self._inflight.get(seq)
        if pending is None or pending.parts is None:
            return  # already acknowledged (or never carried): a stale NEED
        wanted = [i for i in need.missing if i < len(pending.parts)]
        if wanted:
            pending.wanted, pending.cursor = wanted, 0

    def _heard_at(self) -> float:
        """When the peer last showed it is there, for the silence rule (docs/protocol.md 7.7):
        its last valid frame; in version 5 its last frame of any kind (a damaged frame is a
        peer talking through a noisy line, not a silent one)."""
        return self._last_frame if self.version >= 5 else self._last_rx

    def _meets(self, hello: Hello) -> bool:
        """Whether ``hello``'s version range meets this end's."""
        return max(MIN_VERSION, hello.proto_min) <= min(self.proto_max, hello.proto_max)

    def _on_hello(self, hello: Hello, new_peer: bool, now: float) -> None:
        """A HELLO whose range meets ours (:meth:`_on_sequenced` refused the others)."""
        self.peer = hello
        self.version = min(self.proto_max, hello.proto_max)
        if self.state == LinkState.INCOMPATIBLE:  # the peer was updated: greet it again
            self._set_state(LinkState.CONNECTING, "a HELLO whose versions meet ours", now)
            if self._hello_seq is None:
                self._start_hello(now)
        elif new_peer and self._greeted and self._hello_seq is None:
            self._start_hello(now)  # it restarted and does not know us yet

    def _on_ack(self, seq: int, now: float) -> None:
        self._last_ack = now  # the peer hears us (7.1: what a failed message then means)
        pending = self._inflight.pop(seq, None)
        if pending is None:
            self.stats.stray_acks += 1
            return
        if seq == self._hello_seq:
            self._hello_seq = None
            self._greeted = True
            if self.state != LinkState.INCOMPATIBLE:
                self._set_state(LinkState.UP, "HELLO acknowledged")
            self._promote(now)
            return
        self.stats.delivered += 1
        self._events.append(Delivered(pending.message, seq, now - pending.first_at, pending.tries))
        self._promote(now)

    def _on_nak(self, seq: int, nak: Nak) -> None:
        self.stats.naks_received += 1
        pending = self._inflight.pop(seq, None)
        if pending is None:
            return
        if seq == self._hello_seq:
            self._hello_seq = None
            self._set_state(LinkState.INCOMPATIBLE,
                            f"the {self.peer_role.name.lower()} refused our "
                            f"HELLO ({nak.reason.name}): update the older side")
            return
        self._fail(pending, f"NAK {nak.reason.name}", nak.reason)

    # -- bytes out -----------------------------------------------------------------------------

    def _ack(self, frame: Frame, now: float) -> bool:
        """ACK ``frame`` (a burst for an urgent one); False for another copy of a burst already
        answered within ACK_HOLDOFF (not answered: the same transmission)."""
        ack = encode(Ack(), frame.seq, version=min(frame.version, self.proto_max))
        if not frame.flags & FLAG_URGENT:
            self._out += ack
            return True
        last = self._ack_burst_at.get(frame.seq)
        if last is not None and now - last < self.config.ack_holdoff:
            return False  # another copy of a burst already answered with a burst
        if len(self._ack_burst_at) > 64:
            self._ack_burst_at = {s: t for s, t in self._ack_burst_at.items() if now - t < 1.0}
        self._ack_burst_at[frame.seq] = now
        self._out += ack * self.config.urgent_copies
        return True

    def _remember(self, seq: int, refused: tuple[NakReason, int] | None) -> None:
        """Remember an answered seq for duplicates (docs/protocol.md 7.2), the last
        ``dedup_memory`` of them."""
        self._seen[seq] = refused
        if len(self._seen) > self.config.dedup_memory:
            del self._seen[next(iter(self._seen))]

    def _refuse(self, seq: int, reason: NakReason, refused_type: int) -> None:
        """NAK a message of the peer (7.3) and, once its HELLO was heard, remember how
        (7.2): a later frame or PART of that seq, whatever it holds, is answered with the same
        NAK and never acted on (the sender is told one thing about one seq)."""
        if self.peer is not None and seq:
            if seq not in self._seen:
                self._remember(seq, (reason, refused_type))
            elif self._seen[seq] is not None:
                reason, refused_type = self._seen[seq]
        # a HELLO's NAK goes in the HELLO's version byte, 1 (7.5), whatever the session's
        self._nak(seq, reason, refused_type,
                  MIN_VERSION if refused_type == MsgType.HELLO else None)

    def _nak(self, seq: int, reason: NakReason, refused_type: int,
             version: int | None = None) -> None:
        """NAK in the session's version, or ``version`` (a HELLO's NAK carries the HELLO's
        version byte, 1: no session version holds for a peer whose range does not meet)."""
        self._out += encode(Nak(reason, refused_type), seq,
                            version=self.version if version is None else version)
        self.stats.naks_sent += 1

    def _take_seq(self) -> int:
        seq = self._next_seq
        self._next_seq = seq % 0xFFFF + 1  # 1..65535; 0 marks unsequenced frames
        return seq

    def _start_hello(self, now: float) -> None:
        hello = Hello(self.role, self.boot_id, self.software, MIN_VERSION, self.proto_max)
        pending = _Pending(self._take_seq(), hello, True)  # a burst, as PAUSE (7.5)
        self._hello_seq = pending.seq
        self._inflight[pending.seq] = pending
        self._transmit(pending, now)

    def _promote(self, now: float) -> None:
        if not self._greeted or self.state == LinkState.INCOMPATIBLE:
            return  # nothing but HELLO until the peer has reset its duplicate memory for us
        while self._urgent_q:
            pending = self._urgent_q.popleft()
            self._inflight[pending.seq] = pending
            self._transmit(pending, now)
        normal = sum(1 for p in self._inflight.values() if not p.urgent)
        # version 5: the base carries one command at a time, so that the module joins its
        # commands in the order they were sent (7.11; PARTs of several would join shortest first)
        window = 1 if self.role == Role.BASE and self.version >= 5 else self.config.window
        while self._normal_q and normal < window:
            pending = self._normal_q.popleft()
            self._inflight[pending.seq] = pending
            self._transmit(pending, now)
            normal += 1

    def _transmit(self, pending: _Pending, now: float) -> None:
        flags = (FLAG_URGENT if pending.urgent else 0) | (FLAG_RETRY if pending.tries else 0)
        # HELLO goes out in the lowest version, which every peer reads (its layout is frozen)
        version = MIN_VERSION if isinstance(pending.message, Hello) else self.version
        if pending.message.since() > version:  # the peer went back to an older version
            self._inflight.pop(pending.seq, None)
            self._fail(pending, f"{pending.message.TYPE.name} needs protocol version "
                       f"{pending.message.since()}; the {self.peer_role.name.lower()} now speaks "
                       f"{version}")
            return
        if self._carries(pending, version):
            body = encode_body(pending.message, pending.seq, 0, version)
            pending.parts = [encode(part, pending.seq, 0, version) for part in split_body(body)]
            pending.wanted, pending.cursor = list(range(len(pending.parts))), 0
            pending.first_at = now
            pending.tries = 1
            pending.next_at = now + self.config.carry_timeout
            self.stats.sent += 1
            return  # the carousel writes the PARTs
        frame = encode(pending.message, pending.seq, flags, version)
        self._out += frame * self.config.urgent_copies if pending.urgent else frame
        if pending.tries:
            self.stats.retransmissions += 1
        else:
            pending.first_at = now
            self.stats.sent += 1
        pending.tries += 1
        pending.next_at = now + self.config.retry_interval

    def _carry_since(self) -> int:
        """The first version in which this end carries its messages in PARTs (7.11): 3 for
        the module, 5 for the base."""
        return 3 if self.role == Role.MODULE else 5

    def _carries(self, pending: _Pending, version: int) -> bool:
        """Whether ``pending`` goes as PARTs: every sequenced message but the urgent ones
        (PAUSE, RESUME, HELLO), from :meth:`_carry_since` on (docs/protocol.md 7.11)."""
        return version >= self._carry_since() and not pending.urgent

    def _tries_allowed(self, pending: _Pending) -> int:
        """Transmissions of a whole frame before it has failed: MAX_TRIES; in version 5 (but
        for HELLO, which has its own schedule) as many as fit in CARRY_TIMEOUT (7.1)."""
        cfg = self.config
        if self.version < 5 or isinstance(pending.message, Hello):
            return cfg.max_tries
        return max(cfg.max_tries, round(cfg.carry_timeout / cfg.retry_interval))

    def _run_carousel(self, now: float) -> None:
        """Write PARTs of the carried messages in flight, round robin over the messages and
        over each one's wanted parts, at ``part_share`` of the line's bytes per second."""
        carried = [p for p in self._inflight.values() if p.parts is not None]
        if not carried:
            self._part_clock = None
            return
        if self.version < self._carry_since():  # the peer came back older: send them whole
            for pending in carried:
                pending.parts = pending.wanted = None
                pending.tries, pending.next_at = 0, now
            return
        rate = self.config.baud / 10 * self.config.part_share
        if self._part_clock is None:
            self._part_credit = 24.0  # one PART at once
        else:
            self._part_credit = min(64.0, self._part_credit + (now - self._part_clock) * rate)
        self._part_clock = now
        while self._part_credit > 0:
            self._carousel = (self._carousel + 1) % len(carried)
            pending = carried[self._carousel]
            wanted = pending.wanted or list(range(len(pending.parts)))  # type: ignore[arg-type]
            index = wanted[pending.cursor % len(wanted)]
            pending.cursor = (pending.cursor + 1) % len(wanted)
            frame = pending.parts[index]  # type: ignore[index]
            self._out += frame
            self._part_credit -= len(frame)
            self.stats.parts_sent += 1

    def _give_up(self, pending: _Pending, now: float) -> None:
        del self._inflight[pending.seq]
        why = (f"no ACK from the {self.peer_role.name.lower()} after {pending.tries} tries "
               f"{self.config.retry_interval * 1000:.0f} ms apart")
        if pending.parts is not None:
            why = (f"no ACK from the {self.peer_role.name.lower()} {self.config.carry_timeout:g} s "
                   f"after the first of its {len(pending.parts)} PARTs")
        if pending.seq == self._hello_seq:
            self._hello_seq = None
            self._next_hello = now + self.config.hello_interval
            if self.state == LinkState.UP:  # a re-greeting after the peer restarted went unanswered
                self._set_state(LinkState.FAULTY, f"HELLO: {why}", now)
            return
        self._fail(pending, why)
        if self.version >= 5 and self._last_ack > pending.first_at:
            return  # 7.1: the peer acknowledged ours meanwhile; it hears us, the link is up
        if self.state != LinkState.INCOMPATIBLE:
            self._set_state(LinkState.FAULTY,
                            f"{pending.message.TYPE.name} seq {pending.seq}: {why}; "
                            "check the cable, the baud rate and that the base is running", now)

    def _fail(self, pending: _Pending, reason: str, nak: NakReason | None = None) -> None:
        self.stats.failed += 1
        self._events.append(SendFailed(pending.message, pending.seq, reason, nak))

    def _set_state(self, new: LinkState, why: str, now: float | None = None) -> None:
        if new != self.state:
            old, self.state = self.state, new
            if new == LinkState.FAULTY:
                self._next_hello = self._now(now)  # probe with HELLO at once
            self._events.append(StateChanged(old, new, why))

    def _now(self, now: float | None) -> float:
        return self.clock() if now is None else now
