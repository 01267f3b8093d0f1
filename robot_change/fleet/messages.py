"""The fleet's topics and JSON messages (UTF-8 JSON objects, one per MQTT message).

Topics, under a prefix (``fleet.topic_prefix``, default ``robot-change``)::

    <prefix>/<robot>/status             retained, QoS 1: the module's health (online true), or
                                        the Last Will / a clean stop (online false)
    <prefix>/<robot>/checks/<station>   QoS 1: every check told to the base (CHECK results,
                                        WATCH changes and clears)
    <prefix>/<robot>/changes/<station>  QoS 1: the checks that found a change, in short
    <prefix>/<robot>/command            read-only requests to the module ({"request":
                                        "status", "id": ...}); nothing that moves or arms
    <prefix>/<robot>/reply              the answers

A check message is an envelope around the daemon's own report of the check -- the document
``<station>.last-check.json`` holds (``ChangeSet.summary`` in base_link plus the station),
unchanged, under ``"report"``::

    {"robot": "r7", "boot_id": "9f0c...", "report_id": "9f0c...-12", "seq": 12,
     "time": "2026-12-02T10:31:07.123Z", "time_unix": 1796207467.123, "origin": "check",
     "station": "office", "link_report_id": 3, "report": {...}}

A change message has the same envelope (the same ``report_id``) and, taken from that report
under the same names, ``outcome``, ``offset_base`` (the robot's offset from its station pose,
base_link), ``mount`` and ``regions`` (each with its ``base`` box and centroid).  ``report_id``
is unique per robot: a receiver drops a message whose ``report_id`` it has seen on that topic
(a report is sent again when the broker's acknowledgement was lost).
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterable
from typing import Any

from robot_change import json_text

__all__ = ["READ_ONLY_REQUESTS", "Topics", "change_message", "check_message", "decode",
           "encode", "envelope", "parse_request", "utc_text"]

#: Requests the command topic answers.  None of them moves the robot, arms or disarms.
READ_ONLY_REQUESTS = ("status",)
#: Keys of the daemon's check report a change message carries.
CHANGE_KEYS = ("outcome", "offset_base", "mount", "regions")


class Topics:
    """The topic names of one robot (``robot``) or of every robot (``robot="+"``, filters)."""

    def __init__(self, prefix: str, robot: str) -> None:
        self.prefix, self.robot = prefix, robot
        self.base = f"{prefix}/{robot}"

    @property
    def status(self) -> str:
        return f"{self.base}/status"

    def checks(self, station: str) -> str:
        return f"{self.base}/checks/{station}"

    def changes(self, station: str) -> str:
        return f"{self.base}/changes/{station}"

    @property
    def command(self) -> str:
        return f"{self.base}/command"

    @property
    def reply(self) -> str:
        return f"{self.base}/reply"

    def filters(self, checks: bool = False) -> list[str]:
        """What a receiver subscribes to: status, changes (and every check), replies."""
        wanted = [self.status, self.changes("+"), self.reply]
        return wanted + ([self.checks("+")] if checks else [])

    def kind(self, topic: str) -> tuple[str, str, str] | None:
        """(robot, kind, station) of a topic under the prefix: kind is "status", "checks",
        "changes", "command" or "reply"; None for another topic."""
        head = self.prefix + "/"
        if not topic.startswith(head):
            return None
        levels = topic[len(head):].split("/")
        if len(levels) == 2 and levels[1] in ("status", "command", "reply"):
            return levels[0], levels[1], ""
        if len(levels) == 3 and levels[1] in ("checks", "changes"):
            return levels[0], levels[1], levels[2]
        return None


def utc_text(t: float) -> str:
    """Unix time -> ISO 8601 UTC with milliseconds, e.g. ``2026-12-02T10:31:07.123Z``."""
    seconds = int(t)
    return (time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(seconds))
            + f".{int((t - seconds) * 1000):03d}Z")


def envelope(robot: str, boot_id: str, seq: int, station: str, origin: str,
             link_report_id: int | None, t: float) -> dict[str, Any]:
    """What every report message starts with; ``report_id`` is ``<boot_id>-<seq>``."""
    return {"robot": robot, "boot_id": boot_id, "report_id": f"{boot_id}-{seq}", "seq": seq,
            "time": utc_text(t), "time_unix": round(t, 6), "origin": origin,
            "station": station, "link_report_id": link_report_id}


def check_message(head: dict[str, Any], report: dict[str, Any]) -> dict[str, Any]:
    """The checks topic's message: the envelope and the daemon's report under ``"report"``."""
    return {**head, "report": report}


def change_message(head: dict[str, Any], report: dict[str, Any]) -> dict[str, Any]:
    """The changes topic's message: the envelope and :data:`CHANGE_KEYS` of the report."""
    return {**head, **{key: report.get(key) for key in CHANGE_KEYS}}


def encode(message: dict[str, Any]) -> bytes:
    """A message as compact UTF-8 JSON."""
    return json_text.dumps(message, separators=(",", ":"), ensure_ascii=False).encode("utf-8")


def decode(payload: bytes) -> dict[str, Any]:
    """A message's JSON object; ValueError (with what is wrong) for anything else."""
    try:
        message = json.loads(payload.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"not UTF-8 JSON ({exc})") from None
    if not isinstance(message, dict):
        raise ValueError("not a JSON object")
    return message


def parse_request(payload: bytes) -> tuple[Any, Any, str]:
    """A command-topic request -> (its "id", its "request", "" or why it is refused: not a
    JSON object, or not one of the read-only :data:`READ_ONLY_REQUESTS`)."""
    try:
        message = decode(payload)
    except ValueError as exc:
        return None, None, f"a request is a JSON object such as {{\"request\": \"status\"}}: {exc}"
    request, ident = message.get("request"), message.get("id")
    if not isinstance(ident, (str, int, float, type(None))) or isinstance(ident, bool):
        return None, request, '"id" must be a string or a number'
    if request not in READ_ONLY_REQUESTS:
        return ident, request, (f"unknown request {request!r}: the fleet answers only read-only "
                                f"requests ({', '.join(READ_ONLY_REQUESTS)}); nothing that "
                                "moves or arms the robot comes over the network")
    return ident, request, ""


def versions(extra: Iterable[tuple[str, str]] = ()) -> dict[str, str]:
    """Versions a status message names: python, paho-mqtt, and ``extra``."""
    import platform

    import paho.mqtt

    return {"python": platform.python_version(), "paho_mqtt": paho.mqtt.__version__,
            **dict(extra)}
