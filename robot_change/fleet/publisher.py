"""Publisher: a robot's reports and status to the fleet's broker, never in the robot's way.

    publisher = Publisher(settings, "robot-7", Spool(folder, 64 << 20), status=lambda: {...})
    publisher.start()
    publisher.report("office", report_document, changed=True)   # returns at once
    publisher.close()

Threads and queues (nothing grows without bound, nothing here is waited for by the caller)::

    caller    report(): a bounded in-memory queue (when full, the oldest item is dropped and
              counted: queue_dropped); never blocks, never touches the disk or the network
    writer    queue -> envelope (robot, boot id, report id, time) -> spool (atomic files)
    network   spool -> broker, oldest first, QoS 1, up to ``inflight`` unacknowledged; a
              message leaves the spool on the broker's PUBACK (MQTT 5: one that says
              refused keeps it, and the connection is dropped as refused, retried at the
              longest backoff); the retained status (every ``status_every_s`` when it
              changed, and on request) with its Last Will; read-only requests on the
              command topic; reconnects with hw.backoff

A report is written to the spool before it is sent, so a broker that is down, a network that
drops, or a daemon that is killed loses nothing the spool can hold: what was not acknowledged
is sent again, in order, after the next connection -- by this process or by the next one on
the same spool folder.  A message sent again after a lost acknowledgement reaches subscribers
twice with the same ``report_id``; they drop the second (robot_change.fleet.receiver).
"""

from __future__ import annotations

import logging
import queue
import select
import socket
import threading
import time
import uuid
from collections.abc import Callable
from typing import Any

import paho.mqtt.client as mqtt

from hw.backoff import Backoff
from robot_change.errors import FleetError
from robot_change.fleet import messages
from robot_change.fleet.connection import BrokerSettings, new_client, open_connection, refusal
from robot_change.fleet.messages import Topics
from robot_change.fleet.spool import Spool
from robot_change.throttle import Throttled

__all__ = ["Publisher"]

log = logging.getLogger(__name__)

_STOP = object()


class Publisher:
    """One robot's side of the fleet (module docstring).

    ``settings``: the broker.  ``robot``: the robot id (a topic level).  ``spool``: where
    reports wait.  ``status()``: the module's status (a JSON-ready dict, called on the network
    thread; keep it quick).  ``versions``: more versions for the status message.
    ``queue_size``: reports that may wait for the writer.  ``inflight``: spooled messages sent
    and not yet acknowledged.  ``backoff``: first and longest wait between connection attempts
    (seconds).
    """

    def __init__(self, settings: BrokerSettings, robot: str, spool: Spool, *,
                 prefix: str = "robot-change", status: Callable[[], dict] | None = None,
                 versions: dict[str, str] | None = None, queue_size: int = 256,
                 inflight: int = 10, status_every_s: float = 0.5,
                 backoff: tuple[float, float] = (0.5, 15.0)) -> None:
        self.settings = settings
        self.robot = robot
        self.spool = spool
        self.topics = Topics(prefix, robot)
        self.boot_id = uuid.uuid4().hex
        self.started = time.time()
        self._status = status or dict
        self._versions = messages.versions((versions or {}).items())
        self._queue: queue.Queue = queue.Queue(maxsize=queue_size)
        self._inflight_max = inflight
        self._status_every = status_every_s
        self._backoff = Backoff(*backoff)
        self._lock = threading.Lock()
        self._seq = 0
        self._stop = threading.Event()
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._wake_w.setblocking(False)
        self._threads: list[threading.Thread] = []
        self._throttled = Throttled(log, every=60.0)
        self._fail_keys: set[str] = set()
        # counters and state (read by counts() from any thread)
        self.queue_dropped = 0
        self.lost = 0  # reports that could not be written to the spool
        self.sent = 0  # spooled messages the broker acknowledged
        self.state = "down"  # "connecting", "up", "down"
        self.last_error = ""
        # the network thread's own
        self._client: mqtt.Client | None = None
        self._up = False
        self._refused = ""
        self._held = False  # the broker refused a message: reconnect at the longest backoff
        self._inflight: dict[int, int] = {}  # mid -> spool seq
        self._topics: dict[int, str] = {}  # mid -> topic, of the messages not acknowledged
        self._sent_upto = 0
        self._requests: list[tuple[Any, Any, str]] = []  # (id, request, error)
        self._status_sent: dict | None = None
        self._status_at = 0.0
        self._offline_mid: int | None = None
        self._offline_acked = threading.Event()

    # -- the caller's side ----------------------------------------------------------------------

    def start(self) -> None:
        """Start the writer and network threads."""
        for name, target in (("writer", self._writer_main), ("network", self._network_main)):
            thread = threading.Thread(target=self._guard(name, target),
                                      name=f"rc-fleet-{name}", daemon=True)
            self._threads.append(thread)
            thread.start()

    def report(self, station: str, document: dict | Callable[[], dict], *,
               origin: str = "check", link_report_id: int | None = None,
               changed: bool = False) -> str:
        """Queue a check's report (``document``, or a function that makes it, called on the
        writer thread) for the checks topic, and for the changes topic when ``changed``.
        Returns its report id at once; never blocks."""
        with self._lock:
            self._seq += 1
            seq = self._seq
        self._put((seq, station, origin, link_report_id, time.time(), document, changed))
        return f"{self.boot_id}-{seq}"

    def counts(self) -> dict[str, Any]:
        """The fleet's side of the status: connection, spool and queue counts."""
        with self._lock:
            out = {"broker": self.settings.url, "connection": self.state,
                   "last_error": self.last_error, "sent": self.sent,
                   "queue_dropped": self.queue_dropped, "lost": self.lost}
        out["spool"] = self.spool.counts()
        return out

    def close(self, timeout: float = 0.5) -> None:
        """Write what is queued to the spool, tell the broker the robot is going offline
        (retained status) when connected, disconnect.  Waits at most ``timeout`` seconds;
        what is unsent stays in the spool for the next start."""
        end = time.monotonic() + timeout
        self._put(_STOP)
        for thread in self._threads:
            if thread.name.endswith("writer"):
                thread.join(max(0.0, end - time.monotonic() - 0.1))
        self._stop.set()
        self._poke()
        for thread in self._threads:
            thread.join(max(0.01, end - time.monotonic()))

    def _put(self, item: Any) -> None:
        """Queue ``item``; when the queue is full, the oldest item makes room (counted)."""
        while True:
            try:
                self._queue.put_nowait(item)
                return
            except queue.Full:
                try:
                    self._queue.get_nowait()
                except queue.Empty:
                    continue
                with self._lock:
                    self.queue_dropped += 1
                self._throttled("queue-full", logging.WARNING, "fleet: the report queue is "
                                "full; the oldest report was dropped")

    def _guard(self, name: str, target: Callable[[], None]) -> Callable[[], None]:
        def run() -> None:
            while True:
                try:
                    target()
                    return
                except Exception:  # noqa: BLE001 -- a bug here must never reach the robot
                    log.exception("fleet: the %s thread failed; restarting it", name)
                    if self._stop.wait(1.0):
                        return
        return run

    def _poke(self) -> None:
        try:
            self._wake_w.send(b"x")
        except OSError:
            pass

    # -- writer thread --------------------------------------------------------------------------

    def _writer_main(self) -> None:
        while True:
            item = self._queue.get()
            if item is _STOP:
                return
            seq, station, origin, link_report_id, t, document, changed = item
            try:
                report = document() if callable(document) else document
                head = messages.envelope(self.robot, self.boot_id, seq, station, origin,
                                         link_report_id, t)
                self.spool.append(self.topics.checks(station),
                                  messages.encode(messages.check_message(head, report)))
                if changed:
                    self.spool.append(self.topics.changes(station),
                                      messages.encode(messages.change_message(head, report)))
            except OSError as exc:
                with self._lock:
                    self.lost += 1
                self._throttled("spool", logging.ERROR, "fleet: cannot write report %s to the "
                                "spool %s (%s); it is lost", seq, self.spool.folder,
                                exc.strerror or exc)
            except Exception:  # noqa: BLE001 -- a report that cannot be made is logged, not fatal
                with self._lock:
                    self.lost += 1
                log.exception("fleet: cannot make report %s of %s", seq, station)
            self._poke()

    # -- network thread -------------------------------------------------------------------------

    def _network_main(self) -> None:
        while not self._stop.is_set():
            if self._client is None:
                if not self._connect():
                    self._stop.wait(self._backoff.next())
                    continue
            if not self._turn():
                self._drop_connection()
                self._stop.wait(self._backoff.cap if self._held else self._backoff.next())
        self._say_goodbye()

    def _set_state(self, state: str, error: str | None = None) -> None:
        with self._lock:
            self.state = state
            if error is not None:
                self.last_error = error

    def _connect(self) -> bool:
        will = (self.topics.status, messages.encode(self._offline("connection lost")), 1, True)
        self._set_state("connecting")
        self._up, self._refused, self._held = False, "", False
        self._inflight.clear()
        self._topics.clear()
        self._sent_upto = 0
        try:
            client = new_client(self.settings, f"robot-change-{self.robot}", will=will, v5=True)
            client.on_connect = self._on_connect
            client.on_publish = self._on_publish
            client.on_message = self._on_message
            open_connection(client, self.settings)
        except FleetError as exc:
            self._failed(str(exc), lasting=not exc.transient)
            return False
        self._client = client
        self._connect_deadline = time.monotonic() + self.settings.connect_timeout_s
        return True

    def _failed(self, why: str, lasting: bool = False) -> None:
        """Say why there is no connection: once, then at most once a minute while it lasts
        (an error when a setting must change, a warning when the broker may come back)."""
        self._set_state("down", why)
        key = f"fail-{why}"
        self._fail_keys.add(key)
        self._throttled(key, logging.ERROR if lasting else logging.WARNING,
                        "fleet: %s; reports wait in the spool (%d queued), retrying", why,
                        len(self.spool))

    def _drop_connection(self) -> None:
        client, self._client = self._client, None
        was_up, self._up = self._up, False
        if client is not None:
            try:
                client.disconnect()
            except Exception:  # noqa: BLE001 -- the socket may be gone already
                pass
        if self._refused:
            self._failed(self._refused, lasting=True)
        elif was_up:
            self._failed(f"{self.settings.url}: connection lost")
        elif time.monotonic() < self._connect_deadline:
            self._failed(f"{self.settings.url}: the broker closed the connection before "
                         "accepting it (a TLS or protocol mismatch? see the broker's log)")
        else:
            self._failed(f"{self.settings.url}: no CONNACK from the broker within "
                         f"{self.settings.connect_timeout_s:g} s")

    def _turn(self) -> bool:
        """One turn of the network loop; False when the connection is gone."""
        client = self._client
        assert client is not None
        sock = client.socket()
        if sock is None:
            return False
        pending = sock.pending() if hasattr(sock, "pending") else 0
        writing = [sock] if client.want_write() else []
        try:
            readable, writable, _ = select.select([sock, self._wake_r], writing, [],
                                                  0.0 if pending else 0.25)
        except (OSError, ValueError):
            return False
        if self._wake_r in readable:
            try:
                self._wake_r.recv(4096)
            except OSError:
                pass
        if (sock in readable or pending) and client.loop_read() != mqtt.MQTT_ERR_SUCCESS:
            return False
        if sock in writable and client.loop_write() != mqtt.MQTT_ERR_SUCCESS:
            return False
        if client.loop_misc() != mqtt.MQTT_ERR_SUCCESS or self._refused:
            return False
        if not self._up:
            return time.monotonic() < self._connect_deadline
        return self._pump(client)

    def _pump(self, client: mqtt.Client) -> bool:
        """Answer requests, publish the status when due, send spooled messages."""
        for ident, request, error in self._requests:
            reply: dict[str, Any] = {"robot": self.robot, "id": ident, "request": request}
            if error:
                reply["error"] = error
            else:
                reply["status"] = self._status_message()
            if self._publish(client, self.topics.reply, messages.encode(reply)).rc:
                return False
            if not error:
                self._status_at = 0.0  # the retained status too
        self._requests.clear()
        now = time.monotonic()
        if now - self._status_at >= self._status_every:
            self._status_at = now
            message = self._status_message()
            body = {k: v for k, v in message.items() if k not in ("time", "time_unix")}
            if body != self._status_sent:
                if self._publish(client, self.topics.status, messages.encode(message),
                                 retain=True).rc:
                    return False
                self._status_sent = body
        room = self._inflight_max - len(self._inflight)
        if room > 0:
            for seq in self.spool.pending(self._sent_upto, room):
                self._sent_upto = seq
                message = self.spool.read(seq)
                if message is None:
                    continue
                info = self._publish(client, *message)
                if info.rc:
                    return False
                self._inflight[info.mid] = seq
        return True

    def _publish(self, client: mqtt.Client, topic: str, payload: bytes, *,
                 retain: bool = False) -> mqtt.MQTTMessageInfo:
        """QoS 1 publish, its topic kept until the broker acknowledges (or refuses) it."""
        info = client.publish(topic, payload, 1, retain)
        if not info.rc:
            self._topics[info.mid] = topic
        return info

    def _status_message(self) -> dict[str, Any]:
        try:
            body = dict(self._status())
        except Exception as exc:  # noqa: BLE001 -- the status is reported, never fatal
            body = {"status_error": f"{type(exc).__name__}: {exc}"}
        t = time.time()
        return {"robot": self.robot, "online": True, "boot_id": self.boot_id,
                "time": messages.utc_text(t), "time_unix": round(t, 6),
                "started": messages.utc_text(self.started), **body,
                "fleet": self.counts(), "versions": self._versions}

    def _offline(self, reason: str) -> dict[str, Any]:
        return {"robot": self.robot, "online": False, "boot_id": self.boot_id,
                "reason": reason, "started": messages.utc_text(self.started)}

    def _say_goodbye(self) -> None:
        """At close: the retained status says offline (reason "stopped"), then disconnect."""
        client = self._client
        if client is None:
            self._set_state("down")
            return
        if self._up:
            message = {**self._offline("stopped"), "time": messages.utc_text(time.time())}
            info = self._publish(client, self.topics.status, messages.encode(message),
                                 retain=True)
            self._offline_mid = info.mid
            end = time.monotonic() + 0.3
            while (not info.rc and not self._offline_acked.is_set()
                   and time.monotonic() < end and self._turn_quietly(client)):
                pass
        try:
            client.disconnect()
        except Exception:  # noqa: BLE001
            pass
        self._client = None
        self._set_state("down")

    def _turn_quietly(self, client: mqtt.Client) -> bool:
        sock = client.socket()
        if sock is None:
            return False
        try:
            readable, _, _ = select.select([sock], [sock] if client.want_write() else [], [],
                                           0.05)
        except (OSError, ValueError):
            return False
        if client.want_write() and client.loop_write():
            return False
        return not (readable and client.loop_read())

    # -- paho callbacks (on the network thread) -------------------------------------------------

    def _on_connect(self, client: mqtt.Client, _userdata: Any, _flags: Any, reason: Any,
                    _properties: Any) -> None:
        if reason.is_failure:
            self._refused = refusal(self.settings, reason)
            return
        self._up = True
        self._backoff.reset()
        self._status_sent, self._status_at = None, 0.0
        self._set_state("up", "")
        for key in self._fail_keys:
            self._throttled.forget(key)
        self._fail_keys.clear()
        client.subscribe(self.topics.command, 1)
        log.info("fleet: connected to %s as %s; %d report message(s) in the spool",
                 self.settings.url, self.robot, len(self.spool))

    def _on_publish(self, _client: mqtt.Client, _userdata: Any, mid: int, reason: Any,
                    _properties: Any) -> None:
        topic = self._topics.pop(mid, "?")
        if reason is not None and reason.is_failure:
            # kept: a spooled message stays for the next connection, after the longest
            # backoff; the ACL is the operator's to fix (what was refused is the log's)
            self._inflight.pop(mid, None)
            self._held = True
            self._refused = (f"{self.settings.url}: the broker refused the message on {topic}: "
                             f"{reason}; check its ACL lets this robot's user "
                             f"({self.settings.username or 'anonymous'}) publish on "
                             f"{self.topics.base}/#; reports wait in the spool")
            return
        seq = self._inflight.pop(mid, None)
        if seq is not None:
            # counted before it leaves the spool, so a reader never sees it in neither
            with self._lock:
                self.sent += 1
            self.spool.remove(seq)
        elif mid == self._offline_mid:
            self._offline_acked.set()

    def _on_message(self, _client: mqtt.Client, _userdata: Any, message: mqtt.MQTTMessage
                    ) -> None:
        if message.topic != self.topics.command:
            return
        ident, request, error = messages.parse_request(message.payload)
        if error:
            log.warning("fleet: request refused on %s: %s", message.topic, error)
        self._requests.append((ident, request, error))
        del self._requests[:-16]  # a flood of requests keeps only the newest
