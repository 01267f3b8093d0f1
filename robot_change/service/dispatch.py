"""The link thread's side of the service: events from the link (messages received, delivered,
not delivered, the link's and the port's state) and the dispatch of the base's commands:
CAPTURE_REFERENCE, CHECK and WATCH queued for the controller thread (or refused with NAK BUSY
when the queue is full), the quick ones (STATUS_QUERY, ARM, DISARM, RESUME, STOP, SET_PARAM,
GET_PARAM) answered at once."""

from __future__ import annotations

import logging
import queue
from typing import Any

from robot_change.link.protocol import (
    PARAM_BY_ID,
    Arm,
    BaseHeartbeat,
    CaptureReference,
    Check,
    Disarm,
    Fault,
    FaultCode,
    GetParam,
    Message,
    NakReason,
    ParamValue,
    Pause,
    Resume,
    SetParam,
    StatusQuery,
    Stop,
    Watch,
)
from robot_change.link.session import (
    Delivered,
    LinkState,
    PortProblem,
    Received,
    SendFailed,
    StateChanged,
)
from robot_change.service.params import change_params

__all__ = ["Dispatch"]

log = logging.getLogger("robot_change.service.core")  # the service's log lines keep its name


class Dispatch:
    """The link thread of :class:`robot_change.service.core.Service` (a base class of it: the
    attributes it uses -- runner, link, the command queue, params, base_params, counters, the
    lock -- are the service's)."""

    def _link_main(self) -> None:
        while not self._stop.is_set():
            self.progress.beat("link")
            for event in self.runner.step():
                try:
                    self._on_event(event)
                except Exception:  # noqa: BLE001 -- a bad command must not stop the link
                    log.exception("handling %r failed", event)
                    self.send_fault(FaultCode.INTERNAL_ERROR, "internal error handling a command; "
                                "see the module's log")

    def _on_event(self, event: Any) -> None:
        if isinstance(event, Received):
            self._on_message(event.message)
        elif isinstance(event, Delivered):
            if isinstance(event.message, Fault) and self.stalled:
                self.stall_told.set()
        elif isinstance(event, SendFailed):
            self._throttled(f"failed-{event.message.TYPE.name}", logging.WARNING,
                            "%s seq %d not delivered: %s", event.message.TYPE.name, event.seq,
                            event.reason)
            self.counters["send_failed"] += 1
            if (isinstance(event.message, Pause) and event.nak is None
                    and self.link.state == LinkState.UP):
                # version 5 (docs/protocol.md 7.1): a PAUSE tried for 10 s fails without the
                # link going FAULTY when the base acknowledges our other messages
                self._pause_again("a PAUSE was not acknowledged")
        elif isinstance(event, StateChanged):
            log.log(logging.WARNING if event.new != LinkState.UP else logging.INFO,
                    "link %s: %s", event.new.value, event.why)
            if event.new == LinkState.UP and event.old != LinkState.CONNECTING:
                self._pause_again("link back up")
        elif isinstance(event, PortProblem):
            log.log(logging.INFO if event.up else logging.ERROR, "serial port %s: %s",
                    "back" if event.up else "lost", event.detail)

    def _on_message(self, m: Any) -> None:
        if isinstance(m, BaseHeartbeat):
            self.motion = m.motion
            return
        if isinstance(m, (CaptureReference, Check, Watch)):
            self._admitted = max(0, self._admitted - 1)
            try:
                self._commands.put_nowait(m)
            except queue.Full:  # version 1/2 (version 3 NAKs BUSY before the ACK: _admit)
                self.counters["commands_refused"] += 1
                self.send_fault(FaultCode.COMMAND_REFUSED, f"{m.TYPE.name} {m.station} refused: "
                                f"busy, {self.options.command_queue} commands already waiting "
                                f"({self.counters['commands_refused']} refused so far)",
                                coalesce="busy")
                return
            if self._watch is not None:  # a new command ends the watch at once
                self._cancel.set()
            self._wake.set()
            return
        if isinstance(m, StatusQuery):
            self._send(self.status(), coalesce="status")
        elif isinstance(m, Arm):
            with self._lock:
                self.armed = True
            log.info("armed: a change raises PAUSE")
        elif isinstance(m, Disarm):
            with self._lock:
                self.armed = False
            log.info("disarmed: changes are reported, no PAUSE")
        elif isinstance(m, Resume):
            with self._lock:
                was, self.latched = self.latched, False
            if was:
                log.info("RESUME: pause latch cleared")
        elif isinstance(m, Stop):
            self._cancel.set()
            self._wake.set()
            log.info("STOP")
        elif isinstance(m, GetParam):
            name = PARAM_BY_ID[m.param].name
            self._send(ParamValue(m.param, self.params[name]), coalesce=("param", m.param))
        elif isinstance(m, SetParam):
            self._set_param(m.param, m.value)
        self._refresh_heartbeat(force=True)

    def _set_param(self, pid: int, value: int) -> None:
        name = PARAM_BY_ID[pid].name  # the protocol already NAKed unknown ids and bounds
        with self._lock:
            trial = dict(self.params, **{name: value})
            if trial["watch_m"] > trial["watch_n"]:
                self.send_fault(FaultCode.COMMAND_REFUSED,
                            f"SET_PARAM {name}={value} refused: watch_m ({trial['watch_m']}) "
                            f"must be <= watch_n ({trial['watch_n']})")
                self._send(ParamValue(pid, self.params[name]), coalesce=("param", pid))
                return
            self.params = trial
            self.base_params[name] = value
            if self._watch is not None:
                self._watch.configure(self.params, change_params(self.config, self.params))
        log.info("parameter %s = %d", name, value)
        self._send(ParamValue(pid, value), coalesce=("param", pid))

    def _admit(self, m: Message) -> NakReason | None:
        """Version 3: refuse a command the module cannot take now with NAK BUSY, before it is
        acknowledged (docs/protocol.md 7.12).  Answers to queries are coalesced instead."""
        if not isinstance(m, (CaptureReference, Check, Watch)):
            return None
        # commands admitted in this turn of the link thread are queued after it (_on_message)
        if self.link.version < 3 or (self._commands.qsize() + self._admitted
                                     < self.options.command_queue):
            self._admitted += 1
            return None
        self.counters["commands_refused"] += 1
        self._throttled("busy", logging.WARNING, "%s %s refused (NAK BUSY): %d commands "
                        "already waiting", m.TYPE.name, m.station, self.options.command_queue)
        return NakReason.BUSY
