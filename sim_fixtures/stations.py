"""Table stations as a robot sees them: a table with a few objects on it, the wall behind it and
the floor in front, from a camera on a robot standing before the table, looking down at it.

The osd-tabletop pairs (``sim_fixtures.tabletop``) are table tops *cropped* to the table: no
floor, no walls, the far end of the table cut away.  There, when every object moved, nothing
static is left to pin the pose in the table's plane.  A robot's camera at a table station sees
the table's surroundings too; these scenes are that case, drawn at random from a seed, for the
registration benchmark (``bench/bench_registration.py --station``):

    from sim_fixtures.stations import station_spec
    spec = station_spec(seed=3, change="all_moved")     # a SceneSpec (sim_fixtures.scenes)
    spec = station_spec(3, "all_moved", offset=(0.10, 4.0, 11))  # current 10 cm / 4 deg off
    ref, cur, T_ref_from_cur, intrinsics = station_pair(3, "all_moved", (0.10, 4.0, 11))

Changes: ``none``, ``one_moved`` (one object shifted 8-20 cm and turned), ``one_removed``,
``one_added``, ``all_moved`` (every object on the table shifted 5-25 cm and turned: nothing on
the table stays put).  World frame: x, y on the floor, z up; the table's long side along x.
"""

from __future__ import annotations

import dataclasses
import math
import zlib

import numpy as np

from hw.depth import Intrinsics
from sim_fixtures.noise import KinectNoise
from sim_fixtures.render import Cylinder, Obj, Pose
from sim_fixtures.scenes import (
    SceneSpec,
    box,
    observed_masks,
    pose_offset,
    render_pair,
    room,
    table,
    true_transform,
    truth_masks,
)

__all__ = ["CHANGES", "OFFSET_LEVELS", "StationScene", "station_checks", "station_pair",
           "station_scene", "station_spec"]

#: The kinds of change a station scene can be drawn with.
CHANGES = ("none", "one_moved", "one_removed", "one_added", "all_moved")


@dataclasses.dataclass(frozen=True)
class _Top:
    """The table top: centre (x, y), half sizes (m) and height (m)."""

    x: float
    y: float
    half_w: float
    half_d: float
    h: float

    def holds(self, x: float, y: float, r: float, margin: float = 0.03) -> bool:
        """Whether a footprint of radius ``r`` at (x, y) lies on the top, ``margin`` inside."""
        return abs(x - self.x) <= self.half_w - r - margin and \
            abs(y - self.y) <= self.half_d - r - margin


def _item(rng: np.random.Generator, name: str, top: _Top, x: float, y: float,
          yaw_deg: float) -> tuple[Obj, float]:
    """A box or an upright cylinder standing on ``top`` at (x, y); with its footprint radius."""
    if rng.random() < 0.6:
        size = (float(rng.uniform(0.08, 0.3)), float(rng.uniform(0.06, 0.2)),
                float(rng.uniform(0.06, 0.3)))
        return box(name, x, y, size, yaw_deg=yaw_deg, z0=top.h), math.hypot(size[0], size[1]) / 2
    r = float(rng.uniform(0.035, 0.08))
    return Obj(name, (Cylinder((x, y, top.h), r, float(rng.uniform(0.08, 0.25))),), (x, y),
               "cylinder"), r


def _free(x: float, y: float, r: float, taken: list[tuple[float, float, float]]) -> bool:
    """Whether a footprint of radius ``r`` at (x, y) keeps 2 cm from every (x, y, r) taken."""
    return all(math.hypot(x - a, y - b) > r + c + 0.02 for a, b, c in taken)


def _place_items(rng: np.random.Generator, top: _Top, n: int, prefix: str,
                 taken: list[tuple[float, float, float]]) -> list[tuple[Obj, float]]:
    """``n`` items (``prefix`` 0, 1, ...) at free random places on ``top``, with their
    footprint radii; their footprints are added to ``taken``."""
    out = []
    while len(out) < n:
        for _attempt in range(200):
            x = float(rng.uniform(top.x - top.half_w, top.x + top.half_w))
            y = float(rng.uniform(top.y - top.half_d, top.y + top.half_d))
            obj, r = _item(rng, f"{prefix}{len(out)}", top, x, y, float(rng.uniform(0, 180)))
            if top.holds(x, y, r) and _free(x, y, r, taken):
                taken.append((x, y, r))
                out.append((obj, r))
                break
        else:
            raise RuntimeError("no room left on the table")  # a bug in the size ranges
    return out


def _moved(rng: np.random.Generator, top: _Top, obj: Obj, r: float, reach: tuple[float, float],
           taken: list[tuple[float, float, float]]) -> Obj:
    """``obj`` shifted by ``reach`` (min, max m) in a random direction on the top and turned by
    15-45 deg, clear of the footprints ``taken`` (its own left out)."""
    x0, y0 = obj.pivot
    for _attempt in range(500):
        d = float(rng.uniform(*reach))
        a = float(rng.uniform(0, 2 * math.pi))
        x, y = x0 + d * math.cos(a), y0 + d * math.sin(a)
        if top.holds(x, y, r) and _free(x, y, r, taken):
            taken.append((x, y, r))
            turn = float(rng.uniform(15, 45)) * (1 if rng.random() < 0.5 else -1)
            return obj.moved(x - x0, y - y0, turn)
    raise RuntimeError(f"no free place on the table to move {obj.name} to")  # a bug in the sizes


def station_spec(seed: int, change: str = "all_moved",
                 offset: tuple[float, float, int] | None = None) -> SceneSpec:
    """A table station drawn from ``seed``, with ``change`` (one of :data:`CHANGES`) between
    the reference and the current layout; ``offset`` (translation m, rotation deg, seed): the
    current camera displaced from the reference camera as :func:`sim_fixtures.scenes.pose_offset`
    does, else the same pose.  The reference is 3 noisy frames, the current 1 (Kinect noise
    with projector shadows)."""
    if change not in CHANGES:
        raise ValueError(f"change must be one of {CHANGES}, got {change!r}")
    rng = np.random.default_rng([seed, 41])
    lx, ly, hh = float(rng.uniform(3.5, 5.0)), float(rng.uniform(3.5, 5.0)), 2.6
    w, d, h = float(rng.uniform(1.0, 1.6)), float(rng.uniform(0.6, 0.85)), \
        float(rng.uniform(0.72, 0.9))
    tx = float(rng.uniform(lx / 2 - 0.5, lx / 2 + 0.5))
    ty = ly - d / 2 - float(rng.uniform(0.0, 0.6))  # its back edge 0-0.6 m from the wall
    top = _Top(tx, ty, w / 2, d / 2, h)
    structure = room(lx, ly, hh) + [table("table", tx, ty, w=w, d=d, h=h)]
    if rng.random() < 0.5:  # a cupboard beside the table, as a room has
        side = 1 if rng.random() < 0.5 else -1
        structure.append(box("cupboard", tx + side * (w / 2 + 0.45), ly - 0.25,
                             (0.6, 0.45, float(rng.uniform(0.8, 1.9)))))
    taken: list[tuple[float, float, float]] = []
    items = _place_items(rng, top, int(rng.integers(3, 5)), "item", taken)
    ref_items = [o for o, _r in items]
    if change == "none":
        cur_items = list(ref_items)
    elif change == "one_removed":
        cur_items = ref_items[1:]
    elif change == "one_added":
        cur_items = ref_items + [o for o, _r in _place_items(rng, top, 1, "new", taken)]
    elif change == "one_moved":
        others = [(x, y, r) for (x, y, r) in taken[1:]]
        cur_items = [_moved(rng, top, items[0][0], items[0][1], (0.08, 0.2), others)] + \
            ref_items[1:]
    else:  # all_moved: each clear of the others' new places
        placed: list[tuple[float, float, float]] = []
        cur_items = [_moved(rng, top, o, r, (0.05, 0.25), placed) for o, r in items]
    # the robot stands 0.3-0.7 m before the table's front edge, its camera 1.1-1.5 m up (a
    # mobile manipulator's head), looking down at a point of the table top near its middle
    standoff = float(rng.uniform(0.3, 0.7))
    cam = (tx + float(rng.uniform(-0.2, 0.2)), ty - d / 2 - standoff,
           float(rng.uniform(1.1, 1.5)))
    at = (tx + float(rng.uniform(-0.15, 0.15)), ty + float(rng.uniform(-0.15, 0.1)))
    yaw = math.degrees(math.atan2(at[1] - cam[1], at[0] - cam[0]))
    pitch = math.degrees(math.atan2(cam[2] - h, math.hypot(at[0] - cam[0], at[1] - cam[1])))
    pose = Pose(cam, yaw, pitch, 0.0)
    current_pose = pose if offset is None else pose_offset(pose, offset[0], offset[1],
                                                           int(offset[2]))
    return SceneSpec(f"station_{seed}_{change}", "station", f"a table station, {change}", change,
                     (lx, ly, hh), tuple(structure + ref_items), tuple(structure + cur_items),
                     pose, current_pose, KinectNoise(), int(seed) * 10 + CHANGES.index(change))


#: Offset levels of a revisit: cm -> (translation m, rotation deg), as the benches use them;
#: 0 is the robot at its station.
OFFSET_LEVELS = {0: (0.0, 0.0), 5: (0.05, 2.0), 10: (0.10, 4.0), 15: (0.15, 6.0)}


@dataclasses.dataclass(frozen=True, eq=False)
class StationScene:
    """One check of a station with its truth, with :class:`sim_fixtures.Scene`'s names for the
    scorers.

    ``reference_frames`` (3, H, W) and ``current`` (H, W): uint16 mm noisy depth (0 = no
    reading); ``T_ref_from_cur`` (4, 4) the true transform; ``truth_appeared`` over the current
    image and ``truth_disappeared`` over the reference image, ``observed_reference`` /
    ``observed_current`` (what the other camera could see): (H, W) bool from the ideal renders
    (``scenes.truth_masks``, ``scenes.observed_masks``).
    """

    name: str
    change: str
    intrinsics: Intrinsics
    reference_frames: np.ndarray
    current: np.ndarray
    T_ref_from_cur: np.ndarray
    truth_appeared: np.ndarray
    truth_disappeared: np.ndarray
    observed_reference: np.ndarray
    observed_current: np.ndarray


def station_scene(seed: int, change: str = "all_moved",
                  offset: tuple[float, float, int] | None = None) -> StationScene:
    """A check of :func:`station_spec` (same arguments): 3 noisy reference frames, 1 noisy
    current frame, and the truth."""
    spec = station_spec(seed, change, offset)
    ref, cur = render_pair(spec)
    frames = np.stack([spec.noise.apply(ref, np.random.default_rng([spec.seed, 0, k]))
                       for k in range(3)])
    draw = 0 if offset is None else int(offset[2])
    current = spec.noise.apply(cur, np.random.default_rng([spec.seed, draw, 1]))
    appeared, disappeared = truth_masks(spec, ref, cur)
    observed_ref, observed_cur = observed_masks(spec, ref, cur)
    return StationScene(spec.name, change, spec.intrinsics, frames, current,
                        true_transform(spec), appeared, disappeared, observed_ref, observed_cur)


def station_pair(seed: int, change: str = "all_moved",
                 offset: tuple[float, float, int] | None = None
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, Intrinsics]:
    """The depth a check of :func:`station_spec` (same arguments) sees: the reference fused
    from 3 noisy frames (per-pixel median), the current one noisy frame, both (H, W) uint16
    mm; the true ``T_ref_from_cur`` (4, 4) and the intrinsics."""
    scene = station_scene(seed, change, offset)
    fused = np.median(scene.reference_frames, axis=0).astype(np.uint16)
    return fused, scene.current, scene.T_ref_from_cur, scene.intrinsics


def station_checks(seeds: int, seed_base: int = 0, tag: str = "", levels=(5, 10, 15)):
    """The checks a bench runs: ``seeds`` layouts from ``seed_base``, every change of
    :data:`CHANGES`, every level of :data:`OFFSET_LEVELS` in ``levels``; yields (name, seed,
    change, offset), the offset's direction drawn from ``tag`` (None at level 0)."""
    for level in levels:
        tm, rd = OFFSET_LEVELS[level]
        for s in range(seeds):
            seed = seed_base + s
            for change in CHANGES:
                draw = zlib.crc32(f"{tag}station{seed}{change}{tm}".encode()) % 100000
                yield (f"station_{change}_{level}cm_{seed}", seed, change,
                       (tm, rd, draw) if level else None)
