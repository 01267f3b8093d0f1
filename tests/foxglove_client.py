"""A Foxglove WebSocket client for the tests, as the Foxglove app is one: the ``websockets``
library speaking foxglove-sdk's subprotocol (``foxglove.sdk.v1``): read the server's
advertised channels, subscribe, take the binary MESSAGE_DATA frames (opcode 1, subscription
id uint32, log time uint64, payload) and decode them with their advertised schema
(protobuf through mcap-protobuf-support's decoder, or JSON).

Every wait is bounded.
"""

from __future__ import annotations

import base64
import json
import struct
import time
from typing import Any

from mcap.decoder import DecoderFactory as McapDecoderFactory
from mcap.records import Schema
from mcap_protobuf.decoder import DecoderFactory
from websockets.sync.client import connect

SUBPROTOCOL = "foxglove.sdk.v1"
MESSAGE_DATA = 1


class JsonDecoderFactory(McapDecoderFactory):
    """The mcap reader's decoder for JSON-encoded channels (mcap ships none)."""

    def decoder_for(self, message_encoding: str, schema: Schema | None) -> Any:
        return json.loads if message_encoding == "json" else None


def mcap_decoders() -> list[McapDecoderFactory]:
    """What reads back every channel of a check: protobuf (mcap-protobuf-support) and JSON."""
    return [DecoderFactory(), JsonDecoderFactory()]


class FoxgloveClient:
    """Connected to ``ws://host:port``; ``channels``: channel id -> its advertisement."""

    def __init__(self, host: str, port: int, timeout: float = 10.0) -> None:
        self._connection = connect(f"ws://{host}:{port}", subprotocols=[SUBPROTOCOL],
                                   compression=None, open_timeout=timeout, max_size=None)
        self.ws = self._connection.__enter__()
        self.channels: dict[int, dict[str, Any]] = {}
        self.subscriptions: dict[int, int] = {}  # subscription id -> channel id
        self.server_info: dict[str, Any] = {}
        self._decoders = DecoderFactory()

    def close(self) -> None:
        self._connection.__exit__(None, None, None)

    def __enter__(self) -> FoxgloveClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def wait_for_channels(self, topics: set[str], timeout: float = 10.0) -> None:
        """Read the server's text messages until ``topics`` are all advertised."""
        end = time.monotonic() + timeout
        while {c["topic"] for c in self.channels.values()} < topics:
            left = end - time.monotonic()
            assert left > 0, f"advertised {sorted(c['topic'] for c in self.channels.values())}"
            self._handle(self.ws.recv(timeout=left))

    def subscribe_all(self) -> None:
        subscriptions = [{"id": n, "channelId": cid} for n, cid in enumerate(self.channels)]
        self.subscriptions = {s["id"]: s["channelId"] for s in subscriptions}
        self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subscriptions}))

    def receive(self, topics: set[str], timeout: float = 20.0
                ) -> dict[str, tuple[int, Any, bytes]]:
        """Messages until one of each of ``topics`` came: topic -> (log time ns, decoded,
        payload)."""
        got: dict[str, tuple[int, Any, bytes]] = {}
        end = time.monotonic() + timeout
        while not topics <= set(got):
            left = end - time.monotonic()
            assert left > 0, f"got {sorted(got)} of {sorted(topics)}"
            frame = self.ws.recv(timeout=left)
            message = self._handle(frame)
            if message is not None:
                topic, stamp, decoded, payload = message
                got[topic] = (stamp, decoded, payload)
        return got

    def _handle(self, frame: str | bytes) -> tuple[str, int, Any, bytes] | None:
        if isinstance(frame, str):
            text = json.loads(frame)
            if text["op"] == "serverInfo":
                self.server_info = text
            elif text["op"] == "advertise":
                self.channels.update({c["id"]: c for c in text["channels"]})
            elif text["op"] == "unadvertise":
                for cid in text["channelIds"]:
                    self.channels.pop(cid, None)
            return None
        assert frame[0] == MESSAGE_DATA, f"unexpected binary opcode {frame[0]}"
        subscription, stamp = struct.unpack_from("<IQ", frame, 1)
        payload = bytes(frame[13:])
        channel = self.channels[self.subscriptions[subscription]]
        return channel["topic"], stamp, self.decode(channel, payload), payload

    def decode(self, channel: dict[str, Any], payload: bytes) -> Any:
        if channel["encoding"] == "json":
            return json.loads(payload)
        assert channel["encoding"] == "protobuf", channel
        schema = Schema(id=channel["id"], name=channel["schemaName"], encoding="protobuf",
                        data=base64.b64decode(channel["schema"]))
        return self._decoders.decoder_for("protobuf", schema)(payload)
