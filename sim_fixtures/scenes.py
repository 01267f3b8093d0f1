"""The catalogue of synthetic scenes: one room, a reference layout and a current layout each.

Every scene names its room, camera poses, noise model and seed; the truth (which objects were
added, removed or moved) is derived by comparing the two layouts object by object
(:func:`diff_layouts`), and the per-pixel masks from the renderer's object-id images
(:func:`truth_masks`).  Nothing here does I/O; ``make_fixtures`` writes the files.

Splits: ``dev`` scenes may be looked at while tuning; ``holdout`` scenes (about a third) are for
checking the chosen defaults only.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np

from hw.depth import Intrinsics
from sim_fixtures.noise import GaussianNoise, KinectNoise
from sim_fixtures.render import Box, Cylinder, Obj, Plane, Pose, Render, render

__all__ = [
    "SceneSpec",
    "Change",
    "SCENES",
    "get_spec",
    "room",
    "box",
    "table",
    "chair",
    "shelf",
    "sofa",
    "bin_",
    "diff_layouts",
    "truth_masks",
    "object_ids",
    "render_pair",
    "change_geometry",
    "POSE_LEVELS",
    "observed_masks",
    "pose_offset",
    "true_transform",
]


# --------------------------------------------------------------------------- building blocks


def room(lx: float, ly: float, height: float) -> list[Obj]:
    """Floor, ceiling and four walls of the room [0, lx] x [0, ly] x [0, height] (metres)."""
    return [
        Obj("floor", (Plane((0, 0, 0), (0, 0, 1)),), kind="structure"),
        Obj("ceiling", (Plane((0, 0, height), (0, 0, -1)),), kind="structure"),
        Obj("wall_south", (Plane((0, 0, 0), (0, 1, 0)),), kind="structure"),
        Obj("wall_north", (Plane((0, ly, 0), (0, -1, 0)),), kind="structure"),
        Obj("wall_west", (Plane((0, 0, 0), (1, 0, 0)),), kind="structure"),
        Obj("wall_east", (Plane((lx, 0, 0), (-1, 0, 0)),), kind="structure"),
    ]


def _place(name: str, parts_local: Sequence, x: float, y: float, yaw_deg: float, kind: str,
           z0: float = 0.0) -> Obj:
    """Parts built around the origin, turned by yaw about it, then moved to (x, y, z0)."""
    obj = Obj(name, tuple(parts_local), (0.0, 0.0), kind)
    obj = obj.moved(0.0, 0.0, yaw_deg).moved(x, y, 0.0)
    if z0:
        obj = Obj(obj.name, tuple(p.transformed(np.eye(3), np.zeros(3), np.array([0, 0, z0]))
                                  for p in obj.parts), obj.pivot, obj.kind)
    return obj


def box(name: str, x: float, y: float, size: Sequence[float], yaw_deg: float = 0.0,
        z0: float = 0.0) -> Obj:
    """A box of ``size`` (w, d, h) m standing at height ``z0`` with its centre above (x, y)."""
    return _place(name, [Box.on_floor(0, 0, size)], x, y, yaw_deg, "box", z0)


def table(name: str, x: float, y: float, w: float = 1.2, d: float = 0.7, h: float = 0.74,
          yaw_deg: float = 0.0) -> Obj:
    """A table: 4 cm top and four 5 cm legs."""
    leg = 0.05
    parts = [Box.on_floor(0, 0, (w, d, 0.04), z0=h - 0.04)]
    for sx in (-1, 1):
        for sy in (-1, 1):
            parts.append(Box.on_floor(sx * (w / 2 - leg), sy * (d / 2 - leg),
                                      (leg, leg, h - 0.04)))
    return _place(name, parts, x, y, yaw_deg, "table")


def chair(name: str, x: float, y: float, yaw_deg: float = 0.0) -> Obj:
    """A chair facing +x at yaw 0: 45 cm seat at 45 cm, backrest to 90 cm, 4 legs."""
    s, leg = 0.45, 0.04
    parts = [Box.on_floor(0, 0, (s, s, 0.04), z0=0.41),
             Box.on_floor(-s / 2 + 0.02, 0, (0.04, s, 0.45), z0=0.45)]
    for sx in (-1, 1):
        for sy in (-1, 1):
            parts.append(Box.on_floor(sx * (s / 2 - leg), sy * (s / 2 - leg), (leg, leg, 0.41)))
    return _place(name, parts, x, y, yaw_deg, "chair")


def shelf(name: str, x: float, y: float, w: float = 0.9, d: float = 0.35, h: float = 1.8,
          boards: int = 5, yaw_deg: float = 0.0) -> Obj:
    """An open shelf facing +x at yaw 0: back, two sides, ``boards`` boards."""
    t = 0.02
    parts = [Box.on_floor(-d / 2 + t / 2, 0, (t, w, h)),
             Box.on_floor(0, -w / 2 + t / 2, (d, t, h)),
             Box.on_floor(0, w / 2 - t / 2, (d, t, h))]
    for i in range(boards):
        z0 = 0.05 + i * (h - 0.1 - t) / (boards - 1)
        parts.append(Box.on_floor(0, 0, (d, w - 2 * t, t), z0=z0))
    return _place(name, parts, x, y, yaw_deg, "shelf")


def sofa(name: str, x: float, y: float, w: float = 1.8, yaw_deg: float = 0.0) -> Obj:
    """A sofa facing +x at yaw 0: base, back, two arms."""
    d = 0.85
    parts = [Box.on_floor(0.05, 0, (d - 0.1, w - 0.3, 0.42)),
             Box.on_floor(-d / 2 + 0.1, 0, (0.2, w, 0.85)),
             Box.on_floor(0, -w / 2 + 0.08, (d, 0.16, 0.6)),
             Box.on_floor(0, w / 2 - 0.08, (d, 0.16, 0.6))]
    return _place(name, parts, x, y, yaw_deg, "sofa")


def bin_(name: str, x: float, y: float, r: float = 0.15, h: float = 0.4) -> Obj:
    """An upright cylinder (waste bin, plant pot)."""
    return Obj(name, (Cylinder((x, y, 0.0), r, h),), (x, y), "cylinder")


def _look(x: float, y: float, height: float, at: tuple[float, float], pitch_deg: float) -> Pose:
    """A camera at (x, y, height) turned toward the floor point ``at``, pitched down."""
    yaw = math.degrees(math.atan2(at[1] - y, at[0] - x))
    return Pose((x, y, height), yaw, pitch_deg, 0.0)


# --------------------------------------------------------------------------- scenes


@dataclasses.dataclass(frozen=True)
class SceneSpec:
    """One scene: a room seen at a reference time and a current time.

    ``reference``/``current``: the objects (room structure included); objects with the same
    name are the same object.  ``frames``: (reference, current) frame counts.
    """

    name: str
    split: str
    description: str
    change: str
    room_size_m: tuple[float, float, float]
    reference: tuple
    current: tuple
    reference_pose: Pose
    current_pose: Pose
    noise: KinectNoise | GaussianNoise
    seed: int
    frames: tuple[int, int] = (3, 3)
    intrinsics: Intrinsics = dataclasses.field(default_factory=Intrinsics.openni_default)
    # The stored scene whose reference recording this one shares (same layout, pose, noise and
    # seed, so the same frames); None: its own.  Current frame k draws its noise from
    # default_rng([seed, current_noise_epoch, k]).
    reference_from: str | None = None
    current_noise_epoch: int = 1


def _office() -> tuple[list[Obj], Pose]:
    lx, ly, hh = 5.0, 4.2, 2.6
    objs = room(lx, ly, hh) + [
        table("desk", 2.9, 3.8, w=1.4, d=0.7),
        chair("desk_chair", 2.7, 3.1, yaw_deg=80),
        shelf("shelf", 4.8, 1.6, w=0.9, yaw_deg=180),
        box("filing_cabinet", 4.7, 3.6, (0.5, 0.6, 1.1)),
        bin_("bin", 3.8, 3.85),
        box("printer_box", 1.4, 3.9, (0.6, 0.45, 0.5)),
    ]
    return objs, _look(0.5, 0.5, 1.0, (3.6, 2.9), 14.0)


def _lounge() -> tuple[list[Obj], Pose]:
    lx, ly, hh = 5.2, 5.0, 2.7
    objs = room(lx, ly, hh) + [
        sofa("sofa", 4.7, 2.6, w=2.0, yaw_deg=180),
        table("coffee_table", 3.5, 2.6, w=1.0, d=0.55, h=0.42, yaw_deg=90),
        chair("armchair_right", 3.3, 1.2, yaw_deg=120),
        chair("armchair_left", 3.4, 4.0, yaw_deg=-110),
        shelf("bookcase", 2.4, 4.82, w=1.2, h=2.0, yaw_deg=-90),
        bin_("plant_pot", 4.9, 0.5, r=0.2, h=0.5),
    ]
    return objs, _look(0.5, 2.4, 0.8, (4.0, 2.6), 10.0)


def _lab() -> tuple[list[Obj], Pose]:
    lx, ly, hh = 4.5, 5.2, 3.0
    objs = room(lx, ly, hh) + [
        table("bench_left", 0.5, 3.3, w=1.8, d=0.8, h=0.9, yaw_deg=90),
        table("bench_right", 4.0, 3.4, w=1.8, d=0.8, h=0.9, yaw_deg=90),
        shelf("rack", 2.3, 5.0, w=1.2, d=0.4, h=1.9, yaw_deg=-90),
        box("crate", 3.2, 4.5, (0.5, 0.4, 0.4), yaw_deg=15),
        chair("stool", 1.4, 3.0, yaw_deg=200),
        bin_("drum", 0.5, 4.8, r=0.25, h=0.8),
    ]
    return objs, _look(2.2, 0.4, 1.2, (2.3, 3.3), 22.0)


def _storage() -> tuple[list[Obj], Pose]:
    lx, ly, hh = 4.0, 4.0, 2.5
    objs = room(lx, ly, hh) + [
        shelf("shelf_a", 3.8, 1.2, w=1.2, d=0.4, h=2.0, yaw_deg=180),
        shelf("shelf_b", 3.8, 2.7, w=1.2, d=0.4, h=2.0, yaw_deg=180),
        box("carton_a", 2.2, 3.6, (0.6, 0.5, 0.5), yaw_deg=5),
        box("carton_b", 2.2, 3.6, (0.4, 0.4, 0.35), yaw_deg=-10, z0=0.5),
        box("carton_c", 2.6, 1.3, (0.5, 0.6, 0.45), yaw_deg=8),
        bin_("barrel", 3.0, 0.4, r=0.22, h=0.7),
    ]
    return objs, _look(0.4, 0.6, 0.9, (3.0, 2.4), 12.0)


def _meeting() -> tuple[list[Obj], Pose]:
    lx, ly, hh = 5.5, 4.5, 2.6
    objs = room(lx, ly, hh) + [
        table("meeting_table", 3.3, 2.3, w=2.0, d=1.0, h=0.74),
        chair("chair_1", 2.75, 1.45, yaw_deg=90),
        chair("chair_2", 3.85, 1.45, yaw_deg=90),
        chair("chair_3", 2.75, 3.15, yaw_deg=-90),
        chair("chair_4", 3.85, 3.15, yaw_deg=-90),
        chair("chair_5", 4.65, 2.3, yaw_deg=180),
        box("sideboard", 5.25, 3.8, (0.45, 1.2, 0.8)),
    ]
    return objs, _look(0.5, 0.8, 1.0, (3.6, 2.4), 16.0)


def _paper_room() -> tuple[list[Obj], Pose]:
    """A plain simulated room in the spirit of the paper's RCIS scenario (Fig. 7)."""
    lx, ly, hh = 6.0, 5.0, 3.0
    objs = room(lx, ly, hh) + [
        table("table", 4.6, 3.9, w=1.4, d=0.8),
        shelf("cupboard", 5.8, 1.5, w=1.0, d=0.45, h=1.9, yaw_deg=180),
        chair("chair", 4.5, 3.2, yaw_deg=90),
    ]
    return objs, _look(0.6, 1.2, 1.2, (4.2, 2.5), 12.0)


def _without(objs: Sequence[Obj], *names: str) -> list[Obj]:
    missing = set(names) - {o.name for o in objs}
    if missing:
        raise KeyError(f"no object(s) {sorted(missing)} in the layout")
    return [o for o in objs if o.name not in names]


def _with_moved(objs: Sequence[Obj], name: str, dx: float, dy: float, dyaw_deg: float = 0.0
                ) -> list[Obj]:
    return [o.moved(dx, dy, dyaw_deg) if o.name == name else o for o in objs]


_JITTER = dict(dx=0.006, dy=-0.007, dz=0.004, dyaw_deg=0.4, dpitch_deg=-0.3, droll_deg=0.2)
"""Camera jitter for the 'robot came back slightly off' scenes: ~1 cm and ~0.5 degrees."""


def _catalogue() -> dict[str, SceneSpec]:
    kinect = KinectNoise()
    specs: list[SceneSpec] = []

    def add(name, split, change, description, room_size, ref, cur, pose, seed,
            cur_pose=None, noise=kinect, frames=(3, 3)):
        specs.append(SceneSpec(
            name, split, description, change, room_size, tuple(ref), tuple(cur), pose,
            cur_pose or pose, noise, seed, frames,
        ))

    office, office_pose = _office()
    office_size = (5.0, 4.2, 2.6)
    add("office_box_added", "dev", "added", "a cardboard box (45x35x30 cm) appears on the floor "
        "about 2.5 m ahead", office_size, office,
        office + [box("new_box", 2.4, 1.6, (0.45, 0.35, 0.3), yaw_deg=20)], office_pose, 101)
    add("office_no_change", "dev", "none", "the same office twice, independent sensor noise",
        office_size, office, office, office_pose, 102)
    add("office_no_change_jitter", "dev", "none_jitter", "no change, but the robot came back "
        "~1 cm / 0.5 deg off its reference pose", office_size, office, office, office_pose, 103,
        cur_pose=office_pose.moved(**_JITTER))
    add("office_small_object", "dev", "small", "a 10 cm cube appears on the floor about 2.5 m "
        "ahead", office_size, office,
        office + [box("small_cube", 2.35, 1.7, (0.1, 0.1, 0.1), yaw_deg=30)], office_pose, 104)

    lounge, lounge_pose = _lounge()
    lounge_size = (5.2, 5.0, 2.7)
    add("lounge_chair_removed", "dev", "removed", "the right armchair is taken away",
        lounge_size, lounge, _without(lounge, "armchair_right"), lounge_pose, 201)
    add("lounge_chair_moved", "holdout", "moved", "the left armchair moves 0.9 m toward the "
        "middle of the room and turns 35 deg", lounge_size, lounge,
        _with_moved(lounge, "armchair_left", -0.4, -0.8, 35.0), lounge_pose, 202)

    lab, lab_pose = _lab()
    lab_size = (4.5, 5.2, 3.0)
    add("lab_crate_moved", "dev", "moved", "the crate moves 1.5 m to the left and toward the "
        "camera, turning 40 deg", lab_size, lab,
        _with_moved(lab, "crate", -1.2, -0.9, -40.0), lab_pose, 301)
    add("lab_two_changes", "dev", "two", "a tool box appears on the right bench and the stool is "
        "removed", lab_size, lab,
        _without(lab, "stool") + [box("tool_box", 3.75, 3.6, (0.5, 0.25, 0.22), yaw_deg=80,
                                      z0=0.9)], lab_pose, 302)

    storage, storage_pose = _storage()
    storage_size = (4.0, 4.0, 2.5)
    add("storage_carton_removed", "holdout", "removed", "the carton on the floor in front of "
        "the shelves is taken away",
        storage_size, storage, _without(storage, "carton_c"), storage_pose, 401)
    add("storage_no_change_jitter", "holdout", "none_jitter", "no change; the robot came back "
        "~1 cm / 0.5 deg off", storage_size, storage, storage, storage_pose, 402,
        cur_pose=storage_pose.moved(dx=-0.005, dy=0.008, dz=-0.003, dyaw_deg=-0.5,
                                    dpitch_deg=0.25, droll_deg=-0.15))
    add("storage_small_object", "holdout", "small", "a 10 cm cube appears on the floor about "
        "3 m ahead", storage_size, storage,
        storage + [box("small_cube", 2.6, 2.0, (0.1, 0.1, 0.1), yaw_deg=-25)], storage_pose, 403)

    meeting, meeting_pose = _meeting()
    meeting_size = (5.5, 4.5, 2.6)
    add("meeting_box_added", "holdout", "added", "a box (60x40x40 cm) appears by the table",
        meeting_size, meeting,
        meeting + [box("new_box", 2.0, 2.1, (0.6, 0.4, 0.4), yaw_deg=-15)], meeting_pose, 501)
    add("meeting_two_changes", "holdout", "two", "chair 1 is pulled out 0.6 m and a backpack-"
        "sized box appears on the table", meeting_size, meeting,
        _with_moved(meeting, "chair_1", 0.5, -0.4, -20.0)
        + [box("backpack", 3.0, 2.2, (0.35, 0.25, 0.45), yaw_deg=30, z0=0.74)],
        meeting_pose, 502)

    paper, paper_pose = _paper_room()
    paper_size = (6.0, 5.0, 3.0)
    paper_cur = paper + [box("new_box", 3.0, 2.2, (0.6, 0.6, 0.6), yaw_deg=10)]
    for sigma, tag, seed in ((0.001, "1mm", 601), (0.01, "10mm", 602), (0.1, "100mm", 603)):
        add(f"paper_sigma_{tag}", "dev", "added", f"the paper's protocol (Table 1): a box "
            f"appears in a simulated room; plain Gaussian depth noise sigma = {sigma} m",
            paper_size, paper, paper_cur, paper_pose, seed, noise=GaussianNoise(sigma))
    specs += _revisits({s.name: s for s in specs}, office, office_pose, lounge, lounge_pose,
                       storage, storage_pose, meeting, meeting_pose)
    return {s.name: s for s in specs}


#: Offset levels of the revisit scenes: name -> (translation m, rotation deg).
POSE_LEVELS = {"pose_2cm": (0.02, 1.0), "pose_5cm": (0.05, 2.0), "pose_10cm": (0.10, 4.0)}
#: The scenes revisited at every level of POSE_LEVELS (the split follows the scene's).
REVISITED = ("office_box_added", "office_no_change", "lounge_chair_removed", "lab_two_changes",
             "storage_carton_removed", "storage_no_change_jitter", "meeting_two_changes")


def pose_offset(pose: Pose, translation_m: float, rotation_deg: float, seed: int) -> Pose:
    """``pose`` moved by ``translation_m`` in a random direction and turned by about
    ``rotation_deg`` about a random axis (yaw, pitch and roll offsets in random shares whose
    root sum of squares is ``rotation_deg``), from ``default_rng(seed)``."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=3)
    a = rng.normal(size=3)
    d *= translation_m / np.linalg.norm(d)
    a *= rotation_deg / np.linalg.norm(a)
    return pose.moved(float(d[0]), float(d[1]), float(d[2]), float(a[0]), float(a[1]),
                      float(a[2]))


def true_transform(spec: SceneSpec) -> np.ndarray:
    """(4, 4) ``T_ref_from_cur`` of ``spec``: current camera frame -> reference camera frame."""
    ref = spec.reference_pose.matrix()
    inv = np.eye(4)
    inv[:3, :3] = ref[:3, :3].T
    inv[:3, 3] = -ref[:3, :3].T @ ref[:3, 3]
    return inv @ spec.current_pose.matrix()


def _revisits(base: dict[str, SceneSpec], office, office_pose, lounge, lounge_pose, storage,
              storage_pose, meeting, meeting_pose) -> list[SceneSpec]:
    """The robot back at a station with a pose error: each scene of :data:`REVISITED` with its
    current camera displaced from the reference camera by each level of :data:`POSE_LEVELS`;
    and two pairs that must end as "not at the station": the office seen from 0.8 m / 25 deg
    away (beyond the default tolerance), and the storage room's reference against a view of
    the meeting room."""
    out = []
    for name in REVISITED:
        spec = base[name]
        for level, (tag, (translation, rotation)) in enumerate(POSE_LEVELS.items()):
            seed = spec.seed * 100 + level
            out.append(dataclasses.replace(
                spec, name=f"{name}_{tag}",
                change=spec.change if spec.change != "none_jitter" else "none",
                description=f"{spec.description}; the robot came back {translation * 100:.0f} cm"
                f" / {rotation:.0f} deg off its reference pose",
                current_pose=pose_offset(spec.reference_pose, translation, rotation, seed),
                reference_from=name, current_noise_epoch=10 + level))
    office_spec = base["office_no_change"]
    out.append(dataclasses.replace(
        office_spec, name="office_far_offset", change="not_at_station",
        description="the office, but the robot stands 0.8 m and 25 deg away from its station",
        current_pose=office_pose.moved(dx=0.55, dy=0.55, dz=0.0, dyaw_deg=25.0),
        reference_from="office_no_change", current_noise_epoch=20))
    storage_spec = base["storage_carton_removed"]
    out.append(dataclasses.replace(
        storage_spec, name="storage_other_room", change="not_at_station",
        description="the storage room's reference, but the robot is in the meeting room",
        current=tuple(meeting), current_pose=meeting_pose, room_size_m=(5.5, 4.5, 2.6),
        reference_from="storage_carton_removed", current_noise_epoch=21))
    return out


#: name -> SceneSpec, in catalogue order.
SCENES: dict[str, SceneSpec] = _catalogue()


def get_spec(name: str) -> SceneSpec:
    """The :class:`SceneSpec` called ``name``; KeyError listing the known names otherwise."""
    try:
        return SCENES[name]
    except KeyError:
        raise KeyError(f"unknown scene {name!r}; known scenes: {', '.join(SCENES)}") from None


# --------------------------------------------------------------------------- truth


@dataclasses.dataclass(frozen=True)
class Change:
    """One changed object: ``kind`` is 'added', 'removed' or 'moved'."""

    kind: str
    name: str
    before: Obj | None
    after: Obj | None


def _same_geometry(a: Obj, b: Obj) -> bool:
    ca, cb = a.corners(), b.corners()
    if ca is None or cb is None:
        return a is b
    return ca.shape == cb.shape and np.allclose(ca, cb, atol=1e-9)


def diff_layouts(reference: Sequence[Obj], current: Sequence[Obj]) -> list[Change]:
    """Objects added (current only), removed (reference only) and moved (same name, other
    geometry), in that order of appearance."""
    ref = {o.name: o for o in reference}
    cur = {o.name: o for o in current}
    changes = []
    for name, obj in ref.items():
        if name not in cur:
            changes.append(Change("removed", name, obj, None))
        elif not _same_geometry(obj, cur[name]):
            changes.append(Change("moved", name, obj, cur[name]))
    for name, obj in cur.items():
        if name not in ref:
            changes.append(Change("added", name, None, obj))
    return changes


def object_ids(spec: SceneSpec) -> dict[str, int]:
    """name -> id (1, 2, ...) over the union of both layouts; shared by both renders."""
    names: list[str] = []
    for obj in list(spec.reference) + list(spec.current):
        if obj.name not in names:
            names.append(obj.name)
    return {n: i + 1 for i, n in enumerate(names)}


def render_pair(spec: SceneSpec) -> tuple[Render, Render]:
    """Ideal renders (reference, current) of ``spec``, projector shadows as its noise needs."""
    ids = object_ids(spec)
    baseline = getattr(spec.noise, "projector_baseline_m", None)
    out = []
    for objs, pose in ((spec.reference, spec.reference_pose), (spec.current, spec.current_pose)):
        out.append(render(objs, pose, spec.intrinsics, [ids[o.name] for o in objs], baseline))
    return out[0], out[1]


def truth_masks(spec: SceneSpec, ref: Render, cur: Render) -> tuple[np.ndarray, np.ndarray]:
    """(appeared, disappeared): (H, W) bool masks.

    appeared (current image): pixels showing an object that was added or moved (its new place);
    disappeared (reference image): pixels showing an object that was removed or moved (its old
    place).
    """
    ids = object_ids(spec)
    changes = diff_layouts(spec.reference, spec.current)
    if spec.change == "not_at_station":  # another place: nothing to compare
        return np.zeros(cur.ids.shape, bool), np.zeros(ref.ids.shape, bool)
    new_ids = [ids[c.name] for c in changes if c.kind in ("added", "moved")]
    gone_ids = [ids[c.name] for c in changes if c.kind in ("removed", "moved")]
    return np.isin(cur.ids, new_ids), np.isin(ref.ids, gone_ids)


def _geometry(obj: Obj, pose: Pose, r: Render, oid: int) -> dict:
    corners_cam = pose.to_camera(obj.corners())
    lo, hi = corners_cam.min(axis=0), corners_cam.max(axis=0)
    mask = r.ids == oid
    visible = r.points[mask]
    return {
        "centroid_m": [round(float(v), 4) for v in (lo + hi) / 2],
        "extent_m": [round(float(v), 4) for v in hi - lo],
        "bbox_min_m": [round(float(v), 4) for v in lo],
        "bbox_max_m": [round(float(v), 4) for v in hi],
        "visible_pixels": int(mask.sum()),
        "visible_centroid_m": (
            [round(float(v), 4) for v in visible.mean(axis=0)] if len(visible) else None),
        "world_bbox_min_m": [round(float(v), 4) for v in obj.corners().min(axis=0)],
        "world_bbox_max_m": [round(float(v), 4) for v in obj.corners().max(axis=0)],
    }


def observed_masks(spec: SceneSpec, ref: Render, cur: Render, min_depth_m: float = 0.4,
                   max_depth_m: float = 5.0, occlusion_m: float = 0.05
                   ) -> tuple[np.ndarray, np.ndarray]:
    """(reference observed by the current camera, current observed by the reference camera):
    (H, W) bool each, from the ideal renders.  A pixel's surface point is observed by the
    other camera when it lands inside the other image at a depth within
    ``min_depth_m..max_depth_m`` and the other render sees nothing nearer there by more than
    ``occlusion_m`` (seeing past the point, where the object was removed, counts as seeing)."""
    T = true_transform(spec)
    out = []
    for own, other, M in ((ref, cur, np.linalg.inv(T)), (cur, ref, T)):
        hit = own.depth > 0
        p = own.points[hit] @ M[:3, :3].T + M[:3, 3]
        intr = spec.intrinsics
        ok = (p[:, 2] >= min_depth_m) & (p[:, 2] <= max_depth_m)
        z = np.where(ok, p[:, 2], 1.0)
        u = np.floor(intr.fx * p[:, 0] / z + intr.cx + 0.5).astype(np.int64)
        v = np.floor(intr.fy * p[:, 1] / z + intr.cy + 0.5).astype(np.int64)
        ok &= (u >= 0) & (v >= 0) & (u < intr.width) & (v < intr.height)
        seen = np.zeros(p.shape[0], bool)
        d = other.depth[v[ok], u[ok]]
        seen[ok] = (d == 0) | (d >= p[ok, 2] - occlusion_m)
        mask = np.zeros(own.depth.shape, bool)
        mask[hit] = seen
        out.append(mask)
    return out[0], out[1]


def change_geometry(spec: SceneSpec, ref: Render, cur: Render) -> list[dict]:
    """The changes as JSON-ready dicts: kind, object, and per side ('before' in the reference
    camera frame, 'after' in the current camera frame) the object's bounding-box centre and
    extent (metres, camera optical frame), its visible pixel count and visible centroid."""
    ids = object_ids(spec)
    out = []
    if spec.change == "not_at_station":
        return out
    for c in diff_layouts(spec.reference, spec.current):
        entry = {"kind": c.kind, "object": c.name, "id": ids[c.name]}
        if c.before is not None:
            entry["before"] = _geometry(c.before, spec.reference_pose, ref, ids[c.name])
        if c.after is not None:
            entry["after"] = _geometry(c.after, spec.current_pose, cur, ids[c.name])
        out.append(entry)
    return out
