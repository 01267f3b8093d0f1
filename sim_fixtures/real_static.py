"""Real static rooms as no-change pairs: nothing in the room changed between the two epochs, so
any change reported is a false alarm (issue 42).

    from sim_fixtures.real_static import static_pairs, load_static_pair
    for name in static_pairs():               # names, in a fixed order
        pair = load_static_pair(name)
        pair.reference, pair.current          # lists of (480, 640) uint16 mm frames (fused
                                              # when there are several)
        pair.intrinsics, pair.within_range, pair.gap_m, pair.gap_deg, pair.split

The data is read by path from ``../shared/data`` beside the checkout (each folder's README.md
says where it comes from and under which licence), never copied into the repository:

* ``sun3d``: an Asus Xtion's study room (``sun3d-studyroom-xtion-50f-pose``), a hand-held camera
  moving 1.2-1.9 cm a frame, with poses (good to ~1 cm): pairs 1-10 frames apart (1-16 cm),
  single frames, and bursts of 3 consecutive frames fused against 3 others ("fused"; the camera
  moves ~3 cm within a burst, harsher than a robot standing still);
* ``pcl-room``: a Kinect-class room seen from 5 spots (``pcl-pairwise-kinect-room-5views``), no
  poses (the gap is what our registration estimated, 11-22 cm between neighbours);
* ``pcl-grabber``: 3 Kinect-class frames of a laptop on a carpet, 0.25 s apart, the camera held
  by hand (``pcl-grabber-seq``): each ordered pair, and two frames fused against the third;
* ``rtabmap``: a robot's Kinect in a lab seen from two spots ~0.5 m apart
  (``rtabmap-kinect-lab-2views``): beyond the promised range, so ``not_at_station`` or
  ``no_change``.

A pair is *within range* when its camera gap is at most 15 cm and 6 degrees (what
registration promises, docs/algorithm.md); such a pair must end ``no_change``, a pair beyond
``no_change`` or ``not_at_station``; none may end ``changed``.

Split (``pair.split``): every pair of these recordings was looked at while the defaults of
issue 42 were set ("tuning"): their figures are not held out.  What is held out lives in
``bench/eval_change.py --heldout-static DIR`` (recordings outside ../shared/data).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from hw.depth import Intrinsics
from hw.images import read_depth_image
from hw.pcd import cloud_to_depth
from hw.pointfile import read_pcd
from sim_fixtures import UnknownScene

__all__ = [
    "DATA_DIR",
    "MAX_GAP_DEG",
    "MAX_GAP_M",
    "StaticDataMissing",
    "StaticPair",
    "load_static_pair",
    "static_pairs",
]

#: ../shared/data beside the repository (read only, never copied in).
DATA_DIR = Path(__file__).resolve().parents[2] / "shared" / "data"
#: The pose range registration promises (docs/algorithm.md, "What is left").
MAX_GAP_M = 0.15
MAX_GAP_DEG = 6.0

_SUN3D = "sun3d-studyroom-xtion-50f-pose"
_SUN3D_CAMERA = Intrinsics(640, 480, 570.342205, 570.342205, 320.0, 240.0)
_KINECT = Intrinsics(640, 480, 525.0, 525.0, 319.5, 239.5)
_GRABBER_CAMERA = Intrinsics(640, 480, 525.0, 525.0, 320.0, 240.0)
#: pcl-room: gaps between the views as our registration estimated them (no poses given), m.
_PCL_GAPS_M = {(1, 2): 0.110, (2, 3): 0.157, (3, 4): 0.222, (4, 5): 0.173}


class StaticDataMissing(UnknownScene):
    """The real data folder is not beside the checkout (a user's clone): tests skip."""


@dataclasses.dataclass(frozen=True)
class StaticPair:
    """Two epochs of one static room: ``reference`` and ``current`` lists of (H, W) uint16 mm
    frames (fuse them when there are several), ``intrinsics``, the camera gap between them
    (``gap_m``, ``gap_deg``; ``pose_known`` False: estimated by registration), whether it is
    ``within_range``, the recording's ``camera``, and ``split``."""

    name: str
    recording: str
    camera: str
    reference: list
    current: list
    intrinsics: Intrinsics
    gap_m: float
    gap_deg: float
    pose_known: bool
    split: str = "tuning"

    @property
    def within_range(self) -> bool:
        return self.gap_m <= MAX_GAP_M and self.gap_deg <= MAX_GAP_DEG


def _folder(name: str, data_dir: Path | None) -> Path:
    folder = (data_dir or DATA_DIR) / name
    if not folder.is_dir():
        raise StaticDataMissing(f"{folder} not found: the real static rooms are read from "
                                "../shared/data beside the project's checkout")
    return folder


def _sun3d_pairs() -> list[str]:
    out = []
    for start in range(3160, 3200, 4):
        for step in (1, 3, 6, 10):
            if start + step <= 3209:
                out.append(f"sun3d-{start}-{start + step}")
    out += [f"sun3d-{b}-{a}" for a, b in ((3162, 3165), (3171, 3177), (3186, 3194))]
    out += [f"sun3d-fused-{a}-{b}" for a, b in ((3160, 3166), (3175, 3181), (3190, 3200))]
    out += [f"sun3d-{a}-{b}" for a, b in ((3160, 3190), (3165, 3209))]  # beyond the range
    return out


def static_pairs() -> list[str]:
    """Every pair's name, in a fixed order."""
    pcl = [f"pcl-room-{a}-{b}" for a, b in _PCL_GAPS_M] + \
        [f"pcl-room-{b}-{a}" for a, b in _PCL_GAPS_M]
    grabber = [f"pcl-grabber-{a}-{b}" for a in range(3) for b in range(3) if a != b] + \
        ["pcl-grabber-fused-01-2", "pcl-grabber-fused-12-0"]
    return _sun3d_pairs() + pcl + grabber + ["rtabmap-17-154", "rtabmap-154-17"]


def _pose_gap(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    rel = np.linalg.inv(b) @ a
    angle = np.degrees(np.arccos(np.clip((np.trace(rel[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)))
    return float(np.linalg.norm(rel[:3, 3])), float(angle)


def _sun3d(name: str, data_dir: Path | None) -> StaticPair:
    folder = _folder(_SUN3D, data_dir) / "frames"
    fused = name.startswith("sun3d-fused-")
    a, b = (int(v) for v in name.rsplit("-", 2)[-2:])
    span = 3 if fused else 1
    read = [read_depth_image(folder / f"frame-{i:06d}.depth.png") for i in
            list(range(a, a + span)) + list(range(b, b + span))]
    pose = {i: np.loadtxt(folder / f"frame-{i:06d}.pose.txt") for i in (a, b)}
    gap_m, gap_deg = _pose_gap(pose[a], pose[b])
    return StaticPair(name, _SUN3D, "Asus Xtion", read[:span], read[span:], _SUN3D_CAMERA,
                      gap_m, gap_deg, True)


def _pcl_room(name: str, data_dir: Path | None) -> StaticPair:
    folder = _folder("pcl-pairwise-kinect-room-5views", data_dir)
    a, b = (int(v) for v in name.rsplit("-", 2)[-2:])
    depth = [cloud_to_depth(read_pcd(folder / f"capture{i:04d}.pcd"), name)[0] for i in (a, b)]
    gap = _PCL_GAPS_M[(min(a, b), max(a, b))]
    return StaticPair(name, "pcl-pairwise-kinect-room-5views", "Kinect-class", [depth[0]],
                      [depth[1]], _KINECT, gap, 2.0, False)


def _pcl_grabber(name: str, data_dir: Path | None) -> StaticPair:
    folder = _folder("pcl-grabber-seq", data_dir)
    frames = [read_depth_image(p) for p in sorted(folder.glob("frame_*_depth.tiff"))]
    if name.startswith("pcl-grabber-fused-"):
        refs, cur = name.rsplit("-", 2)[-2:]
        reference, current = [frames[int(i)] for i in refs], [frames[int(cur)]]
    else:
        a, b = (int(v) for v in name.rsplit("-", 2)[-2:])
        reference, current = [frames[a]], [frames[b]]
    # hand-held, 0.25 s apart: a few millimetres (the data's README: median |dz| 3-10 mm)
    return StaticPair(name, "pcl-grabber-seq", "Kinect-class", reference, current,
                      _GRABBER_CAMERA, 0.01, 0.5, False)


def _rtabmap(name: str, data_dir: Path | None) -> StaticPair:
    folder = _folder("rtabmap-kinect-lab-2views", data_dir)
    a, b = name.rsplit("-", 2)[-2:]
    depth = [read_depth_image(folder / "depth" / f"{i}.png") for i in (a, b)]
    return StaticPair(name, "rtabmap-kinect-lab-2views", "Kinect-class", [depth[0]], [depth[1]],
                      _KINECT, 0.5, 3.0, False)


def load_static_pair(name: str, data_dir: Path | None = None) -> StaticPair:
    """One pair by name (:func:`static_pairs`).  Raises :class:`StaticDataMissing` when the
    data is not there and :class:`sim_fixtures.UnknownScene` for an unknown name."""
    if name not in static_pairs():
        raise UnknownScene(f"unknown static pair {name!r}; known: {', '.join(static_pairs())}")
    for prefix, loader in (("sun3d-", _sun3d), ("pcl-room-", _pcl_room),
                           ("pcl-grabber-", _pcl_grabber), ("rtabmap-", _rtabmap)):
        if name.startswith(prefix):
            return loader(name, data_dir)
    raise AssertionError(name)  # every name has a prefix above
