"""What a check and a fault become on the wire: CHANGE_REPORT regions and CHECK_RESULT in the
protocol's units and field widths, FAULT texts without this machine's paths and within their
length."""

from __future__ import annotations

import re

from robot_change.change.mount import CameraMount
from robot_change.change.results import ChangeSet
from robot_change.change.results import Region as ChangeRegion
from robot_change.link.protocol import (
    REGIONS_PER_PART,
    WEAK_BITS,
    CheckOutcome,
    CheckResult,
    Region,
    RegionKind,
)

__all__ = ["MAX_REPORT_REGIONS", "check_result", "wire_text"]

#: Most CHANGE_REPORT regions sent for one report (the largest first): 255 parts of 11.
MAX_REPORT_REGIONS = 255 * REGIONS_PER_PART
_FAULT_TEXT = 200


def _clip(value: float, lo: int, hi: int) -> int:
    return int(min(hi, max(lo, round(value))))


def _wire_regions(regions: list[ChangeRegion], mount: CameraMount | None = None
                  ) -> list[Region]:
    """change.Region (metres) -> protocol.Region (mm, clipped to the field widths): in the
    camera optical frame (protocol version 1), or with ``mount`` in base_link (version 2)."""
    out = []
    for r in regions:
        kind = RegionKind.APPEARED if r.kind == "appeared" else RegionKind.DISAPPEARED
        if mount is None:
            centre, size = r.centroid, r.extent
        else:
            lo, hi = r.base_box(mount)
            centre, size = mount.to_base(r.centroid[None])[0], hi - lo
        centroid = tuple(_clip(v * 1000.0, -32768, 32767) for v in centre)
        extent = tuple(_clip(v * 1000.0, 0, 65535) for v in size)
        out.append(Region(kind, centroid, extent, _clip(r.n_points, 0, 0xFFFF_FFFF)))
    return out


def check_result(station: str, changes: ChangeSet, mount: CameraMount, report_id: int = 0
                 ) -> CheckResult:
    """The CHECK_RESULT (protocol version 2) of a ChangeSet: outcome and the robot's offset
    from its station pose in base_link (mm, centi-degrees), fitness, unobserved share, weak
    directions."""
    offset = mount.offset(changes.registration)
    outcome = {"changed": CheckOutcome.CHANGED, "no_change": CheckOutcome.NO_CHANGE,
               "not_at_station": CheckOutcome.NOT_AT_STATION}[changes.outcome]
    if outcome == CheckOutcome.CHANGED and not report_id:
        outcome = CheckOutcome.NO_CHANGE  # every region was below the wire's size limits
    weak = 0
    for name in offset.weak:
        weak |= WEAK_BITS[name]
    return CheckResult(
        station, outcome, report_id,
        tuple(_clip(v * 1000.0, -32768, 32767) for v in offset.translation_m),
        tuple(_clip(v * 100.0, -32768, 32767) for v in offset.rpy_deg),
        _clip(changes.registration.fitness * 1000.0, 0, 1000),
        _clip(changes.unobserved_fraction * 1000.0, 0, 1000), weak)


_ABSOLUTE_PATH = re.compile(r"(?<![\w.~-])/[^\s'\"(),;:]+")


def wire_text(text: str) -> str:
    """A FAULT text for the wire: every absolute path of this machine replaced by its last
    component, the name of the file, folder or port (``/dev/ttyUSB0`` -> ``ttyUSB0``); the log
    keeps the whole text (docs/protocol.md, FAULT)."""
    def name(match: re.Match) -> str:
        return match.group(0).rstrip("/").rsplit("/", 1)[-1] or "/"
    return _ABSOLUTE_PATH.sub(name, text)


def _short(text: str) -> str:
    text = " ".join(str(text).split())
    return text if len(text.encode()) <= _FAULT_TEXT else text.encode()[:_FAULT_TEXT - 3].decode(
        "utf-8", "ignore") + "..."

