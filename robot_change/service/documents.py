"""The JSON documents the daemon gives out, one format each.

``check_report``: a check as ``reports/<station>.last-check.json`` holds it and as the fleet's
checks topic carries it (under ``"report"``; robot_change.fleet.messages):
:meth:`robot_change.change.results.ChangeSet.summary` with the camera's mounting (regions and the
robot's offset from its station pose in base_link) and the station's name.

``status_document``: the module's health for the fleet's retained status topic: what the base
sees in HEARTBEAT / STATUS and a little more (the last CHECK, recent faults), without what
changes every frame (fps, frame counts), so the retained message changes only when the state
does.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Protocol

from robot_change.change.mount import CameraMount
from robot_change.change.results import ChangeSet
from robot_change.link.session import Link

__all__ = ["StatusSource", "check_report", "status_document"]

#: Counters of the service a status names.
STATUS_COUNTERS = ("checks", "pauses", "not_at_station", "stalls", "commands_refused",
                   "send_failed")


def check_report(station: str, changes: ChangeSet, mount: CameraMount) -> dict[str, Any]:
    """A check's report: ``changes.summary(mount)`` and ``"station"``."""
    report = changes.summary(mount)
    report["station"] = station
    return report


class StatusSource(Protocol):
    """What a status is made of: :class:`robot_change.service.core.Service` is one (this
    module does not import it: the service imports this one)."""

    link: Link
    stalled: str
    counters: Mapping[str, int]

    @property
    def camera_ok(self) -> bool: ...

    @property
    def camera_error(self) -> str: ...

    @property
    def camera_losses(self) -> int: ...

    def state_fields(self) -> dict[str, Any]: ...


def status_document(service: StatusSource) -> dict[str, Any]:
    """The service's status for the fleet (module docstring); quick, any thread."""
    body = service.state_fields()
    body.update({
        "camera": {"ok": service.camera_ok, "error": service.camera_error,
                   "losses": service.camera_losses},
        "link": {"state": service.link.state.value, "protocol": service.link.version},
        "stalled": service.stalled,
        "counters": {name: int(service.counters[name]) for name in STATUS_COUNTERS},
    })
    return body
