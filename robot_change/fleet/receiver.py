"""Receiver: the subscribing side of the fleet (``robot-change fleet-tail``, a dashboard's
collector): robots' status, changes and, when asked, every check, each new message handed to a
callback once -- a report sent again after a lost acknowledgement is dropped by its report id.

    def show(message: Incoming) -> None: print(message.robot, message.kind, message.payload)
    Receiver(BrokerSettings("mqtt://broker.lan"), show).run(stop_event)

``session``: a persistent session (a fixed client id, clean_session false, QoS 1
subscriptions): the broker keeps what is published while the receiver is away and hands it
over when it comes back.
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import threading
import time
import uuid
from collections.abc import Callable
from typing import Any

import paho.mqtt.client as mqtt

from hw.backoff import Backoff
from robot_change import validate
from robot_change.errors import FleetError
from robot_change.fleet import messages
from robot_change.fleet.connection import BrokerSettings, new_client, open_connection, refusal
from robot_change.fleet.messages import Topics

__all__ = ["Incoming", "Receiver"]

log = logging.getLogger(__name__)

#: Report ids remembered per receiver to drop duplicates (the oldest are forgotten).
REMEMBERED_IDS = 100_000


@dataclasses.dataclass(frozen=True)
class Incoming:
    """One message: ``kind`` is "status", "checks", "changes" or "reply"; ``payload`` its
    JSON object (``error`` says why there is none: not JSON, not an object)."""

    topic: str
    robot: str
    kind: str
    station: str
    payload: dict[str, Any]
    error: str = ""


class Receiver:
    """Subscribe and hand each new message to ``on_message`` (module docstring).

    ``robot``: one robot id, or "+" for all.  ``checks``: every check too, not only changes.
    ``on_state(text)``: connection news (lost, back), for a person to read.
    """

    def __init__(self, settings: BrokerSettings, on_message: Callable[[Incoming], None], *,
                 prefix: str = "robot-change", robot: str = "+", checks: bool = False,
                 session: str | None = None,
                 on_state: Callable[[str], None] | None = None) -> None:
        validate.topic_prefix("fleet-tail", "prefix", prefix)
        if robot != "+":
            validate.plain_name("fleet-tail", "robot", robot, validate.MAX_ROBOT_ID)
        if session is not None:
            validate.plain_name("fleet-tail", "session", session, 64)
        self.settings = settings
        self.topics = Topics(prefix, robot)
        self.checks = checks
        self.session = session
        self._on_message = on_message
        self._on_state = on_state or (lambda text: log.warning("%s", text))
        self._seen: collections.OrderedDict[tuple[str, str, str], None] = collections.OrderedDict()
        self.duplicates = 0
        self._refused = ""
        self._up = False

    def run(self, stop: threading.Event, connect_timeout: float | None = None) -> None:
        """Receive until ``stop`` is set.  The first connection must succeed (else
        :class:`FleetError`); later losses are retried with a back-off and told to
        ``on_state``."""
        backoff = Backoff(0.5, 10.0)
        first = True
        while not stop.is_set():
            try:
                client = self._connect()
                self._pump(client, stop, connect_timeout or self.settings.connect_timeout_s)
                first = False
            except FleetError as exc:
                if first:
                    raise
                self._on_state(f"{exc}; retrying")
                stop.wait(backoff.next())
                continue
            backoff.reset()
            if not stop.is_set():
                self._on_state(f"{self.settings.url}: connection lost; reconnecting")

    def _connect(self) -> mqtt.Client:
        client_id = (f"robot-change-tail-{self.session}" if self.session
                     else f"robot-change-tail-{uuid.uuid4().hex[:12]}")
        client = new_client(self.settings, client_id, clean_session=self.session is None)
        client.on_connect = self._connected
        client.on_message = self._message
        self._refused, self._up = "", False
        open_connection(client, self.settings)
        return client

    def _pump(self, client: mqtt.Client, stop: threading.Event, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        try:
            while not stop.is_set():
                rc = client.loop(0.2)
                if self._refused:
                    raise FleetError(self._refused)
                if not self._up and time.monotonic() > deadline:
                    raise FleetError(f"{self.settings.url}: no CONNACK from the broker within "
                                     f"{timeout:g} s", transient=True)
                if rc != mqtt.MQTT_ERR_SUCCESS:
                    if not self._up:
                        raise FleetError(f"{self.settings.url}: the connection closed before "
                                         "the broker accepted it", transient=True)
                    return
        finally:
            try:
                client.disconnect()
            except Exception:  # noqa: BLE001 -- the socket may be gone already
                pass

    def _connected(self, client: mqtt.Client, _userdata: Any, _flags: Any, reason: Any,
                   _properties: Any) -> None:
        if reason.is_failure:
            self._refused = refusal(self.settings, reason)
            return
        self._up = True
        client.subscribe([(topic, 1) for topic in self.topics.filters(self.checks)])

    def _message(self, _client: mqtt.Client, _userdata: Any, message: mqtt.MQTTMessage) -> None:
        where = self.topics.kind(message.topic)
        if where is None:
            return
        robot, kind, station = where
        try:
            payload, error = messages.decode(message.payload), ""
        except ValueError as exc:
            payload, error = {}, str(exc)
        report_id = payload.get("report_id")
        if kind in ("checks", "changes") and isinstance(report_id, str):
            key = (kind, robot, report_id)
            if key in self._seen:
                self.duplicates += 1
                return
            self._seen[key] = None
            if len(self._seen) > REMEMBERED_IDS:
                self._seen.popitem(last=False)
        self._on_message(Incoming(message.topic, robot, kind, station, payload, error))
