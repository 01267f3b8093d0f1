"""The session's data types: how a :class:`~robot_change.link.session.Link` is tuned
(:class:`LinkConfig`) and what it reports (:class:`LinkState`, the events, :class:`LinkStats`).

Part of :mod:`robot_change.link.session`, which re-exports every name.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum
from typing import Any

from robot_change.link.protocol import URGENT_COPIES, Message, NakReason


class LinkState(str, Enum):
    """CONNECTING until our first HELLO is acked; FAULTY after a failed message or peer silence."""

    CONNECTING = "connecting"
    UP = "up"
    FAULTY = "faulty"
    INCOMPATIBLE = "incompatible"


@dataclass(frozen=True)
class LinkConfig:
    """Timing and sizes of the session; the defaults are the protocol's (docs/protocol.md)."""

    retry_interval: float = 0.1
    max_tries: int = 5
    window: int = 4
    heartbeat_interval: float = 0.1
    silence_timeout: float = 1.0
    hello_interval: float = 0.5
    urgent_copies: int = URGENT_COPIES
    ack_holdoff: float = 0.05
    dedup_memory: int = 128
    max_queue: int = 256
    #: Line speed (bytes per second = baud / 10): paces the PART carousel (version 3).
    baud: int = 115200
    #: Share of the line the PARTs of carried messages may take (the rest stays free for
    #: urgent bursts, ACKs and heartbeats).
    part_share: float = 0.75
    #: A carried message not acknowledged this long after its first PART has failed.
    carry_timeout: float = 10.0
    #: The base's NEED for one message at most this often.
    need_interval: float = 0.05
    #: Half-joined carried messages a receiver keeps (the oldest is dropped beyond).
    max_assemblies: int = 8

    @classmethod
    def for_baud(cls, baud: int, **overrides: Any) -> LinkConfig:
        """The defaults, slowed for slow lines (docs/protocol.md 7.4): a retry never comes before
        an urgent burst and its ACK burst have crossed the line (2.5x their air time), and the
        ACK holdoff covers a whole burst (1.5x).  At 115200 baud and above: the plain defaults.
        """
        byte_time = 10 / baud  # 8N1
        burst = cls.urgent_copies * 10 * byte_time  # PAUSE / RESUME copies, 10 bytes each
        acks = cls.urgent_copies * 9 * byte_time  # the ACK burst, 9 bytes a copy
        values: dict[str, Any] = {"retry_interval": max(cls.retry_interval, 2.5 * (burst + acks)),
                                  "ack_holdoff": max(cls.ack_holdoff, 1.5 * burst),
                                  "baud": baud}
        values.update(overrides)
        return cls(**values)


# events ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Received:
    """A message from the peer, delivered once (heartbeats: every one)."""

    message: Message
    seq: int


@dataclass(frozen=True)
class Delivered:
    """The peer acknowledged our message after ``tries`` transmissions, ``rtt`` s after the
    first."""

    message: Message
    seq: int
    rtt: float
    tries: int


@dataclass(frozen=True)
class SendFailed:
    """Our message was not delivered: no ACK after every try, a NAK, or the queue overflowed."""

    message: Message
    seq: int
    reason: str
    nak: NakReason | None = None


@dataclass(frozen=True)
class StateChanged:
    """The link changed state; ``why`` says what happened in words an operator can act on."""

    old: LinkState
    new: LinkState
    why: str


@dataclass(frozen=True)
class PortProblem:
    """The runner's port failed or came back (``up``); ``detail`` says what to do."""

    up: bool
    detail: str


Event = Received | Delivered | SendFailed | StateChanged | PortProblem


@dataclass
class LinkStats:
    """Counters since the link was made."""

    bytes_in: int = 0
    bytes_out: int = 0
    frames_in: int = 0
    sent: int = 0
    retransmissions: int = 0
    delivered: int = 0
    failed: int = 0
    duplicates: int = 0
    naks_sent: int = 0
    naks_received: int = 0
    stray_acks: int = 0  # ACKs for nothing in flight: extra copies of an urgent ACK burst
    heartbeats_sent: int = 0
    heartbeats_received: int = 0
    parts_sent: int = 0  # version 3: PART frames written
    parts_received: int = 0
    needs_sent: int = 0
    needs_received: int = 0
    carried: int = 0  # carried messages joined (each once)
    carried_bad: int = 0  # joined bodies that did not decode (a false CRC match): started again
    assemblies_dropped: int = 0
    before_hello: int = 0  # sequenced messages refused because the peer had sent no HELLO
