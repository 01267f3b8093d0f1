"""Real static rooms as no-change pairs: nothing in the room changed between the two epochs, so
any change reported is a false alarm (issue 42).

    from sim_fixtures.real_static import static_pairs, load_static_pair
    for name in static_pairs():               # names, in a fixed order
        pair = load_static_pair(name)
        pair.reference, pair.current          # lists of (H, W) uint16 mm frames (fused
                                              # when there are several)
        pair.intrinsics, pair.within_range, pair.gap_m, pair.gap_deg, pair.split
        pair.profile                          # the built-in noise profile to check it with
    for name in heldout_pairs():              # recordings outside ../shared/data
        pair = load_heldout_pair(name, data_dir=None)    # default HELDOUT_DIR

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
  ``no_change``;
* ``azure``: the one real Azure Kinect (time-of-flight) frame (``azure-kinect-tof-1capture``,
  read by :mod:`hw.azure_kinect`, 640 x 576 NFOV unbinned) against itself re-rendered
  from a camera 3 cm and 5 cm to the side (``sim_fixtures.tabletop.seen_from``: what the
  first camera did not see stays a hole): within range.  The same readings on both sides, so
  this checks the time-of-flight picture (holes, multipath, 1 mm steps, a hexagonal field of
  view) and the ``azure_kinect`` profile, not the camera's noise between epochs.

Each pair names the built-in noise profile (robot_change.noise) to check it with
(``pair.profile``): ``xtion`` for the Xtion, ``kinect_v1`` for the Kinect-class cameras,
``azure_kinect`` for the Azure Kinect.

A pair is *within range* when its camera gap is at most 15 cm and 6 degrees (what
registration promises, docs/algorithm.md); such a pair must end ``no_change``, a pair beyond
``no_change`` or ``not_at_station``; none may end ``changed``.

Split (``pair.split``): every pair of these recordings was looked at while the defaults of
issue 42 were set ("tuning"): their figures are not held out.

Held out (``pair.split`` "held-out"; :func:`heldout_pairs`, :func:`load_heldout_pair`): two
recordings kept outside ../shared/data, in ``HELDOUT_DIR`` (``../heldout-data`` beside the
checkout, i.e. /work/heldout-data; a caller passes another folder), run only by
``bench/eval_change.py --heldout [DIR]`` when the defaults are to be judged, never while they
are set:

* ``7scenes``: Microsoft 7-Scenes' red kitchen (``7scenes-redkitchen-kinect-100f-pose``), a
  hand-held Kinect v1, two windows of 50 frames (0-49 and 600-649) with KinectFusion poses:
  pairs 1-20 frames apart within one window (0.1-13 cm, up to ~9 degrees: within and beyond
  the range), a few reversed, bursts of 3 frames fused against 3 others ("fused"), and each
  window's first frame against its last (16 and 29 cm: beyond);
* ``apc``: an Amazon Picking Challenge shelf bin seen by a RealSense F200 on a robot arm from a
  3 x 5 grid of views (``apc-shelf-realsense-f200-15views-pose``; the raw depth camera's
  frames, depth closer than 0.2 m masked: the camera's own foam pads), each pair of
  neighbouring views both ways (6-8 cm, 10-12.5 degrees): all beyond the range, so they must
  simply not end ``changed``.  No built-in profile is an F200's; they are checked with
  ``realsense_d435`` (Intel's short-range active camera: near limit 0.3 m, ~1-2 mm at 0.5 m),
  chosen from the datasheets before any of them was run.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from hw.depth import Intrinsics
from hw.imagefile import read_image
from hw.images import read_depth_image
from hw.pcd import cloud_to_depth
from hw.pointfile import read_pcd
from robot_change.noise.profile import DEFAULT_PROFILE
from sim_fixtures import UnknownScene

__all__ = [
    "DATA_DIR",
    "HELDOUT_DIR",
    "MAX_GAP_DEG",
    "MAX_GAP_M",
    "StaticDataMissing",
    "StaticPair",
    "heldout_pairs",
    "load_heldout_pair",
    "load_static_pair",
    "read_apc_depth",
    "static_pairs",
]

#: ../shared/data beside the repository (read only, never copied in).
DATA_DIR = Path(__file__).resolve().parents[2] / "shared" / "data"
#: ../heldout-data beside the repository: the held-out recordings (read only, never copied in).
HELDOUT_DIR = Path(__file__).resolve().parents[2] / "heldout-data"
#: The pose range registration promises (docs/algorithm.md, "What is left").
MAX_GAP_M = 0.15
MAX_GAP_DEG = 6.0

_SUN3D = "sun3d-studyroom-xtion-50f-pose"
_SUN3D_CAMERA = Intrinsics(640, 480, 570.342205, 570.342205, 320.0, 240.0)
_KINECT = Intrinsics(640, 480, 525.0, 525.0, 319.5, 239.5)
_GRABBER_CAMERA = Intrinsics(640, 480, 525.0, 525.0, 320.0, 240.0)
#: pcl-room: gaps between the views as our registration estimated them (no poses given), m.
_PCL_GAPS_M = {(1, 2): 0.110, (2, 3): 0.157, (3, 4): 0.222, (4, 5): 0.173}
_AZURE = "azure-kinect-tof-1capture"
#: azure: how far to the side (m) the second camera stands.
_AZURE_OFFSETS_CM = (3, 5)

_7SCENES = "7scenes-redkitchen-kinect-100f-pose"
#: 7-Scenes' nominal depth intrinsics (the recording's camera-intrinsics.txt).
_7SCENES_CAMERA = Intrinsics(640, 480, 585.0, 585.0, 320.0, 240.0)
#: 7scenes: the two windows' first frames (50 frames each).
_7SCENES_WINDOWS = (0, 600)
_APC = "apc-shelf-realsense-f200-15views-pose"
#: apc: neighbouring views of the 3 x 5 grid (rows 0-4, 9-5, 10-14, snaking: consecutive
#: frames are neighbours, and the views above and below one another), 6-8 cm apart.
_APC_NEIGHBOURS = tuple((i, i + 1) for i in range(14)) + (
    (0, 9), (1, 8), (2, 7), (3, 6), (5, 14), (6, 13), (7, 12), (8, 11))
#: apc: depth closer than this (deci-millimetres, 0.2 m) is the camera's own foam pads.
_APC_NEAR_DMM = 2000


class StaticDataMissing(UnknownScene):
    """The real data folder is not beside the checkout (a user's clone): tests skip."""


@dataclasses.dataclass(frozen=True)
class StaticPair:
    """Two epochs of one static room: ``reference`` and ``current`` lists of (H, W) uint16 mm
    frames (fuse them when there are several), ``intrinsics``, the camera gap between them
    (``gap_m``, ``gap_deg``; ``pose_known`` False: estimated by registration), whether it is
    ``within_range``, the recording's ``camera``, ``split`` ("tuning": looked at while the
    defaults were set; "held-out": not) and ``profile``, the built-in noise profile to build
    both scenes with (``build_scene(..., noise=builtin_profile(pair.profile))``)."""

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
    #: the built-in noise profile (robot_change.noise.profile.BUILTIN) to check the pair with
    profile: str = DEFAULT_PROFILE

    @property
    def within_range(self) -> bool:
        return self.gap_m <= MAX_GAP_M and self.gap_deg <= MAX_GAP_DEG


def _folder(name: str, data_dir: Path | None) -> Path:
    folder = Path(data_dir or DATA_DIR) / name
    if not folder.is_dir():
        raise StaticDataMissing(f"{folder} not found: the real static rooms are read from "
                                "../shared/data beside the project's checkout")
    return folder


def _heldout_folder(name: str, data_dir: Path | None) -> Path:
    folder = Path(data_dir or HELDOUT_DIR) / name
    if not folder.is_dir():
        raise StaticDataMissing(f"{folder} not found: the held-out recordings are read from "
                                f"{HELDOUT_DIR} (or the folder the caller names), outside "
                                "../shared/data")
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
    azure = [f"azure-seen-{cm}cm" for cm in _AZURE_OFFSETS_CM]
    return _sun3d_pairs() + pcl + grabber + ["rtabmap-17-154", "rtabmap-154-17"] + azure


def _7scenes_pairs() -> list[str]:
    out = []
    for w in _7SCENES_WINDOWS:
        out += [f"7scenes-{a}-{a + step}" for a in range(w, w + 40, 8) for step in (1, 3, 10, 20)
                if a + step <= w + 49]
        out += [f"7scenes-{w + b}-{w + a}" for a, b in ((6, 12), (30, 40))]
        out += [f"7scenes-fused-{w + a}-{w + b}" for a, b in ((0, 6), (20, 26), (40, 46))]
        out.append(f"7scenes-{w}-{w + 49}")  # the window's ends: beyond the range
    return out


def heldout_pairs() -> list[str]:
    """Every held-out pair's name, in a fixed order (the names need no data)."""
    apc = [f"apc-{a}-{b}" for a, b in _APC_NEIGHBOURS] + \
        [f"apc-{b}-{a}" for a, b in _APC_NEIGHBOURS]
    return _7scenes_pairs() + apc


def _pose_gap(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    rel = np.linalg.inv(b) @ a
    angle = np.degrees(np.arccos(np.clip((np.trace(rel[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)))
    return float(np.linalg.norm(rel[:3, 3])), float(angle)


def _posed_pair(name: str, recording: str, folder: Path, camera: str, intrinsics: Intrinsics,
                profile: str, split: str) -> StaticPair:
    """A pair of a recording of frames with poses (``frame-NNNNNN.depth.png`` and
    ``.pose.txt`` in ``folder``): ``<prefix>-A-B`` frames A and B, ``<prefix>-fused-A-B`` the 3
    frames from each."""
    a, b = (int(v) for v in name.rsplit("-", 2)[-2:])
    span = 3 if "-fused-" in name else 1
    read = [read_depth_image(folder / f"frame-{i:06d}.depth.png") for i in
            list(range(a, a + span)) + list(range(b, b + span))]
    pose = {i: np.loadtxt(folder / f"frame-{i:06d}.pose.txt") for i in (a, b)}
    gap_m, gap_deg = _pose_gap(pose[a], pose[b])
    return StaticPair(name, recording, camera, read[:span], read[span:], intrinsics, gap_m,
                      gap_deg, True, split=split, profile=profile)


def _sun3d(name: str, data_dir: Path | None) -> StaticPair:
    return _posed_pair(name, _SUN3D, _folder(_SUN3D, data_dir) / "frames", "Asus Xtion",
                       _SUN3D_CAMERA, "xtion", "tuning")


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


def _azure(name: str, data_dir: Path | None) -> StaticPair:
    from hw.depth import open_depth
    from sim_fixtures.tabletop import seen_from

    folder = _folder(_AZURE, data_dir)
    with open_depth(f"mkv:{folder / 'recording.mkv'}") as source:
        frame = source.read()
    depth, camera = frame.depth, frame.intrinsics
    offset_m = int(name.removeprefix("azure-seen-").removesuffix("cm")) / 100.0
    T_new_from_old = np.eye(4)
    T_new_from_old[0, 3] = -offset_m  # the camera moved +x (to its right)
    current = seen_from(depth, camera, T_new_from_old)
    return StaticPair(name, _AZURE, "Azure Kinect", [depth], [current], camera, offset_m, 0.0,
                      True, profile="azure_kinect")


def load_static_pair(name: str, data_dir: Path | None = None) -> StaticPair:
    """One pair by name (:func:`static_pairs`).  Raises :class:`StaticDataMissing` when the
    data is not there and :class:`sim_fixtures.UnknownScene` for an unknown name."""
    if name not in static_pairs():
        raise UnknownScene(f"unknown static pair {name!r}; known: {', '.join(static_pairs())}")
    for prefix, loader in (("sun3d-", _sun3d), ("pcl-room-", _pcl_room),
                           ("pcl-grabber-", _pcl_grabber), ("rtabmap-", _rtabmap),
                           ("azure-", _azure)):
        if name.startswith(prefix):
            return loader(name, data_dir)
    raise AssertionError(name)  # every name has a prefix above


def _7scenes(name: str, data_dir: Path | None) -> StaticPair:
    return _posed_pair(name, _7SCENES, _heldout_folder(_7SCENES, data_dir) / "frames",
                       "Kinect v1", _7SCENES_CAMERA, "kinect_v1", "held-out")


def _apc_info(path: Path) -> dict[str, np.ndarray]:
    """The matrices of an APC ``cam.info.txt``, by their heading ("Depth camera intrinsic
    matrix", "Camera-to-world extrinsic matrix (camera pose) for frame-000000", ...)."""
    if not path.is_file():
        raise StaticDataMissing(f"{path} not found (the recording's camera file)")
    out: dict[str, list] = {}
    heading = None
    for line in path.read_text().splitlines():
        line = line.strip()
        if line.startswith("#"):
            heading = line.lstrip("# ").strip()
            out[heading] = []
        elif line and heading is not None:
            try:
                out[heading].append([float(v) for v in line.split()])
            except ValueError:
                raise ValueError(f"{path}: a row of {heading!r} is not numbers: {line!r}") \
                    from None
    return {k: np.array(v) for k, v in out.items() if v}


def read_apc_depth(path: Path) -> np.ndarray:
    """(480, 640) uint16 mm of an APC depth PNG: 16-bit, deci-millimetres stored bit-rotated
    (``d = ((v << 13) | (v >> 3)) & 0xFFFF``, metres = d / 10000), rounded to millimetres;
    closer than 0.2 m (the camera's own foam pads) set to 0 (no reading)."""
    raw = read_image(path)
    if raw.dtype != np.uint16:
        raise ValueError(f"{path}: expected a 16-bit depth PNG, got {raw.dtype}")
    v = raw.astype(np.uint32)
    dmm = ((v << 13) | (v >> 3)) & 0xFFFF
    mm = (dmm + 5) // 10
    mm[dmm < _APC_NEAR_DMM] = 0
    return mm.astype(np.uint16)


def _apc(name: str, data_dir: Path | None) -> StaticPair:
    folder = _heldout_folder(_APC, data_dir) / "scene-0000"
    info = _apc_info(folder / "cam.info.txt")
    try:
        K = info["Depth camera intrinsic matrix"]
        E = info["Depth-to-color camera extrinsic matrix"]
        a, b = (int(v) for v in name.rsplit("-", 2)[-2:])
        # the poses are the colour camera's; the raw depth camera's is T_color @ E
        pose = {i: info[f"Camera-to-world extrinsic matrix (camera pose) for frame-{i:06d}"] @ E
                for i in (a, b)}
    except KeyError as exc:
        raise ValueError(f"{folder / 'cam.info.txt'}: no {exc} matrix") from None
    camera = Intrinsics(640, 480, float(K[0, 0]), float(K[1, 1]), float(K[0, 2]),
                        float(K[1, 2]))
    depth = [read_apc_depth(folder / "raw" / f"frame-{i:06d}.depth.png") for i in (a, b)]
    gap_m, gap_deg = _pose_gap(pose[a], pose[b])
    return StaticPair(name, _APC, "Intel RealSense F200", [depth[0]], [depth[1]], camera,
                      gap_m, gap_deg, True, split="held-out", profile="realsense_d435")


def load_heldout_pair(name: str, data_dir: Path | str | None = None) -> StaticPair:
    """One held-out pair by name (:func:`heldout_pairs`), read from ``data_dir`` (default
    :data:`HELDOUT_DIR`).  Raises :class:`StaticDataMissing` when the data is not there and
    :class:`sim_fixtures.UnknownScene` for an unknown name."""
    if name not in heldout_pairs():
        raise UnknownScene(f"unknown held-out pair {name!r}; known: "
                           f"{', '.join(heldout_pairs())}")
    for prefix, loader in (("7scenes-", _7scenes), ("apc-", _apc)):
        if name.startswith(prefix):
            return loader(name, None if data_dir is None else Path(data_dir))
    raise AssertionError(name)  # every name has a prefix above
