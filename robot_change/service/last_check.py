"""The files of a station's last CHECK in the report folder: ``<station>.last-check.npz``
(fused depth, the reference's, change masks, region boxes; CHECK_FORMAT) and
``<station>.last-check.json`` (its report), for people and ``robot-change demo``."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from hw.atomic import write_atomically
from robot_change import json_text, npzfile
from robot_change.change.results import ChangeSet
from robot_change.change.results import Region as ChangeRegion
from robot_change.change.scene import SceneModel
from robot_change.service.config import Config
from robot_change.service.documents import check_report

__all__ = ["CHECK_FORMAT", "write_last_check"]

log = logging.getLogger("robot_change.service.core")  # the service's log lines keep its name

#: Format of ``<station>.last-check.npz`` (robot_change.npzfile): the last CHECK's fused depth,
#: the reference's, the change masks (H, W) bool, intrinsics (6,) w h fx fy cx cy, region boxes
#: (R, 10) min xyz, max xyz, centroid xyz (m, camera frame), points; region kinds (R,) 1 / 2.
CHECK_FORMAT = "robot_change.check"


def write_last_check(folder: Path | str | None, config: Config, station: str,
                     reference: SceneModel, depth: np.ndarray, changes: ChangeSet,
                     regions: list[ChangeRegion]) -> None:
    """Write the last check of ``station`` into ``folder`` (nothing when it is None); a failure
    is a warning in the log, never an exception."""
    if folder is None:
        return
    try:
        cam = reference.intrinsics
        boxes = np.array([[*r.bbox_min, *r.bbox_max, *r.centroid, r.n_points]
                          for r in regions], dtype=np.float64).reshape(-1, 10)
        kinds = np.array([1 if r.kind == "appeared" else 2 for r in regions], np.uint8)
        Path(folder).mkdir(parents=True, exist_ok=True)
        npzfile.write(Path(folder) / f"{station}.last-check.npz", CHECK_FORMAT, 1, {
            "depth": depth, "reference_depth": reference.depth,
            "appeared_mask": changes.appeared_mask,
            "disappeared_mask": changes.disappeared_mask,
            "intrinsics": np.array([cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy]),
            "region_boxes": boxes, "region_kinds": kinds}, {"station": station})
        report = check_report(station, changes, config.camera.mount())
        write_atomically(Path(folder) / f"{station}.last-check.json",
                         (json_text.dumps(report, indent=1) + "\n").encode())
    except OSError as exc:  # a full disk, a folder gone: said in one line
        log.warning("could not write the last check of %s to %s: %s", station, folder, exc)
    except Exception:  # noqa: BLE001 -- a picture for people is never worth a fault
        log.warning("could not write the last check of %s to %s", station, folder,
                    exc_info=True)
