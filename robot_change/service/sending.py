"""What the service sends: FAULT, PAUSE, CHECK_RESULT with the CHANGE_REPORT parts or CLEAR, in
the link's protocol version, each check told to the base handed to the fleet afterwards, and
the heartbeat's contents.  ``send_fault``, ``send_pause``, ``send_report`` and
``send_no_change`` are also what a watch calls (robot_change.service.watch.WatchHost)."""

from __future__ import annotations

import logging
import time
from typing import Any

from robot_change.change.results import ChangeSet
from robot_change.change.results import Region as ChangeRegion
from robot_change.fleet.messages import utc_text
from robot_change.link.protocol import (
    V1_FAULT_CODE,
    V1_PAUSE_CAUSE,
    Clear,
    Fault,
    FaultCode,
    Heartbeat,
    Pause,
    PauseCause,
    split_change_report,
)
from robot_change.service.documents import check_report
from robot_change.service.wire import (
    MAX_REPORT_REGIONS,
    _short,
    _wire_regions,
    check_result,
    wire_text,
)

__all__ = ["Sending"]

log = logging.getLogger("robot_change.service.core")  # the service's log lines keep its name


class Sending:
    """The sending side of :class:`robot_change.service.core.Service` (a base class of it: the
    attributes it uses -- runner, link, config, counters, faults, fleet, the lock -- are the
    service's)."""

    def _send(self, message: Any, coalesce: Any = None) -> None:
        try:
            self.runner.send(message, coalesce=coalesce)
        except Exception:  # noqa: BLE001 -- e.g. a message field out of range: log, go on
            log.exception("cannot send %s", type(message).__name__)

    def send_fault(self, code: FaultCode, text: str, coalesce: Any = None) -> None:
        """FAULT to the base; the log has ``text`` whole, the wire without this machine's
        paths (wire_text)."""
        if coalesce is None:
            (log.info if code == FaultCode.CLEARED else log.error)("FAULT %s: %s", code.name, text)
        else:
            self._throttled(f"fault-{coalesce}", logging.ERROR, "FAULT %s: %s", code.name, text)
        self.counters[f"fault_{code.name.lower()}"] += 1
        self.faults.append({"time": utc_text(time.time()), "code": code.name,
                            "text": _short(wire_text(text))})
        if self.link.version < 2:
            code = V1_FAULT_CODE.get(code, code)
        self._send(Fault(code, _short(wire_text(text))), coalesce=coalesce)

    def send_pause(self, cause: PauseCause) -> None:
        with self._lock:
            self.latched = True
            self._last_pause_cause = cause
        self._send(self._pause_of(cause))
        self.counters["pauses"] += 1
        log.warning("PAUSE %s", cause.name)
        self._refresh_heartbeat(force=True)

    def _pause_again(self, why: str) -> None:
        """PAUSE once more while the pause latch is set (the base may not have had it)."""
        if not self.latched:
            return
        log.info("%s with the pause latch set: sending PAUSE again", why)
        self._send(self._pause_of(self._last_pause_cause))

    def _pause_of(self, cause: PauseCause) -> Pause:
        """PAUSE ``cause`` as the session's version has it (version 1: NOT_AT_STATION's and
        the like mapped to its older causes)."""
        return Pause(V1_PAUSE_CAUSE.get(cause, cause) if self.link.version < 2 else cause)

    def send_report(self, station: str, changes: ChangeSet) -> int:
        """CHECK_RESULT (version 2) then the CHANGE_REPORT parts; regions in base_link in
        version 2, in the camera optical frame in version 1."""
        regions = self._kept_regions(changes)
        with self._lock:
            self._report_id = self._report_id % 0xFFFF + 1
            report_id = self._report_id
        v2 = self.link.version >= 2
        mount = self.config.camera.mount()
        if v2:
            self._send(check_result(station, changes, mount, report_id))
        for part in split_change_report(report_id, station,
                                        _wire_regions(regions, mount if v2 else None)):
            self._send(part)
        self._to_fleet(station, changes, report_id)
        return report_id

    def send_no_change(self, station: str, changes: ChangeSet) -> None:
        """CHECK_RESULT (version 2) then CLEAR."""
        if self.link.version >= 2:
            self._send(check_result(station, changes, self.config.camera.mount()))
        self._send(Clear(station))
        self._to_fleet(station, changes)

    def _answer_not_at_station(self, station: str, changes: ChangeSet, what: str) -> None:
        """CHECK_RESULT NOT_AT_STATION (version 2), or FAULT COMMAND_REFUSED (version 1)."""
        offset = self.config.camera.mount().offset(changes.registration)
        # the offset first: a FAULT's text is cut at 200 bytes, the reason is the long part
        text = (f"{what} {station}: not at the station: offset "
                f"{[round(v, 2) for v in offset.translation_m]} m "
                f"{[round(v, 1) for v in offset.rpy_deg]} deg ({changes.not_at_station_reason})")
        log.warning("%s", text)
        self.counters["not_at_station"] += 1
        if self.link.version >= 2:
            self._send(check_result(station, changes, self.config.camera.mount()))
        else:
            self._send(Fault(FaultCode.COMMAND_REFUSED, _short(text)))
        self._to_fleet(station, changes)

    def _to_fleet(self, station: str, changes: ChangeSet, report_id: int | None = None) -> None:
        """A check told to the base goes to the fleet too, after the base's messages: queued
        at once (the report is made on the fleet's writer thread), never waited for."""
        if self.fleet is None:
            return
        mount = self.config.camera.mount()
        self.fleet.report(station, lambda: check_report(station, changes, mount),
                          origin="watch" if self._watch is not None else "check",
                          link_report_id=report_id, changed=report_id is not None)

    def _kept_regions(self, changes: ChangeSet) -> list[ChangeRegion]:
        """The regions of a ChangeSet to report, largest first, at most MAX_REPORT_REGIONS (the
        size limits of the wire's parameters were applied by the check itself:
        robot_change.service.params.change_params)."""
        kept = sorted(changes.regions, key=lambda r: -r.n_points)
        return kept[:MAX_REPORT_REGIONS]

    def _refresh_heartbeat(self, force: bool = False) -> None:
        now = time.monotonic()
        if not force and now - self._heartbeat_at < 0.1:
            return
        self._heartbeat_at = now
        with self._lock:
            beat = Heartbeat(self.reported_state(), self.latched, self.armed,
                             not self.camera_ok or bool(self.stalled),
                             min(0xFFFF, round(self.fps() * 10)),
                             self.last_frame_index & 0xFFFF_FFFF)
        self.runner.set_heartbeat(beat)
