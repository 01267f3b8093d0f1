"""Real table-top pairs (osd-tabletop: Kinect/Xtion, static camera) with truth from the labels.

    from sim_fixtures.tabletop import load_tabletop_pair, tabletop_pairs
    pair = load_tabletop_pair("test10-test11")
    pair.reference, pair.current           # (480, 640) uint16 mm, 0 = no reading / cropped
    pair.truth_appeared                    # (480, 640) bool over the current image
    pair.truth_disappeared                 # (480, 640) bool over the reference image
    seen_from(pair.current, pair.intrinsics, T)  # the current from a displaced camera

The data is not in the repository: it is read by path from ``../shared/data/osd-tabletop``
(beside the checkout; see its README.md), ``derived/<frame>_depth_mm.png`` (uint16 mm) and
``derived/<frame>_label.png`` (uint16: 0 = no point, 1-9 table, >= 20 object, id = label // 10,
ids not consistent across frames).

Truth rule (the free-space idea of ALGORITHM.md §3, decided per pixel; ``M`` =
:data:`TRUTH_MARGIN_MM` = 20 mm):

* appeared (current image): the pixel is labelled *object* in the current frame and the reference
  at that pixel saw something farther away by more than ``M`` -- something new stands in front of
  what was there;
* disappeared (reference image): the same with the frames swapped -- the pixel is labelled
  *object* in the reference and the current frame now sees farther by more than ``M``.

A 0 (no reading) in the *other* frame is never evidence by itself:

* crop: the clouds were cropped (floor, walls, far end of the table removed), and the crop differs
  between frames (learn40 -> learn41, right edge).  A frame's *footprint* is its valid pixels with
  the enclosed holes filled; a pixel outside the other frame's footprint is never truth;
* sensor dropouts and shadows (holes inside the footprint): the hole is filled from its edge
  inward, ring by ring, each pixel taking the *nearest* depth among its 3x3 neighbours already
  known, so a static object with a dropout in one frame is not a change.  Conservative: a new
  object over a hole next to a nearer surface is missed rather than invented (test14 -> test15:
  38 disappeared pixels with the fill before the speck step below, 461 if a hole counted as
  "seen through" -- the added box's shadows on the hidden box).

Last, 8-connected truth specks of fewer than :data:`MIN_REGION_PX` = 20 pixels are dropped: they
are depth-edge flicker along static objects (<= 110 pixels per pair; a 20-pixel patch at 1.2 m is
about 1.2 x 1.2 cm, far below any object here).

Why 20 mm: on pixels labelled table in both frames |dz| has median 0 and p99 <= 10 mm, p99.9 <=
15 mm on every pair (the data README's static-camera check; measured again here); on the
surfaces of static objects (test9 -> test10 front box, test14 -> test15 rear box, test37 ->
test38 can and round tin, learn39 -> learn40 right-hand object) |dz| p99 is 3-6 mm.  20 mm is
twice the worst p99, above every p99.9, and ~2.5 disparity quantisation steps at the farthest
depth (1.67 m: 2.85e-3 z^2 = 8 mm).  Table pixels differing by more than 20 mm: 0-35 per pair,
nearly all within 2 px of an object or a hole.  An object moved by less than ~2 cm along the ray,
or two surfaces within 2 cm, give no truth: pairs where an object only shifted slightly have thin
truth slivers (see sim_fixtures/README.md, per pair).  Moving the margin to 10 or 30 mm changes
the counts by 1-21 %, the slight-shift slivers far more (test13 -> test14 appeared: 2384 / 1366 /
1162 pixels at 10 / 20 / 30 mm, before the speck step).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
from scipy import ndimage

from hw.depth import Intrinsics
from sim_fixtures import UnknownScene

__all__ = [
    "TabletopPair",
    "TabletopDataMissing",
    "tabletop_pairs",
    "load_tabletop_pair",
    "tabletop_truth",
    "changed_objects",
    "footprint",
    "fill_dropouts",
    "drop_specks",
    "TRUTH_MARGIN_MM",
    "MIN_REGION_PX",
    "DEFAULT_DATA_DIR",
    "PAIRS",
]

#: ../shared/data/osd-tabletop beside the repository (read only, never copied in).
DEFAULT_DATA_DIR = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "osd-tabletop"
#: Depth margin (mm) of the truth rule; see the module docstring for why 20.
TRUTH_MARGIN_MM = 20
#: Truth specks smaller than this (8-connected, pixels) are dropped: depth-edge flicker.
MIN_REGION_PX = 20
#: Labels >= this are objects (20-29 object 1, 30-39 object 2, ...); 1-9 is the table.
OBJECT_LABEL_MIN = 20
#: Truth pixels within this many pixels of an object's edge do not make the object a changed
#: one: depth-edge flicker and a neighbour's truth spill there (module docstring: the table's
#: differing pixels lie within 2 px of an object or a hole).
OBJECT_EDGE_PX = 3
SHAPE = (480, 640)

#: name -> (reference frame, current frame, what changes per the data README).
PAIRS: dict[str, tuple[str, str, str]] = {
    "test9-test10": ("test9", "test10",
                     'rear "gittis" box moved/rotated, front box unchanged'),
    "test10-test11": ("test10", "test11",
                      "small green box ADDED in front, large box shifted"),
    "test13-test14": ("test13", "test14",
                      "white box REMOVED (green box shifted slightly)"),
    "test14-test15": ("test14", "test15",
                      'green box removed/hidden, "gittis" box ADDED in front'),
    "test36-test37": ("test36", "test37",
                      "all 3 objects moved (tall tin laid down, can moved, round tin stood on "
                      "edge)"),
    "test37-test38": ("test37", "test38",
                      "one object MOVED (tall tin stood upright), others static"),
    "learn38-learn39": ("learn38", "learn39", "all 4 objects rearranged"),
    "learn39-learn40": ("learn39", "learn40",
                        "a cup removed, another cup swapped, tin shifted (4 -> 3 objects)"),
    "learn40-learn41": ("learn40", "learn41",
                        "pot stacked on tin, cup removed (3 -> 2 objects); crop mask differs at "
                        "right edge"),
}


class TabletopDataMissing(FileNotFoundError):
    """The osd-tabletop folder (or one of its derived images) is not there."""


@dataclasses.dataclass(frozen=True, eq=False)
class TabletopPair:
    """One real pair, one frame per epoch.

    ``reference``/``current``: (480, 640) uint16 depth, mm, 0 = no reading or cropped.
    ``reference_labels``/``current_labels``: (480, 640) uint16 labels (0 none, 1-9 table, >= 20
    object; ids differ between frames).  ``truth_appeared`` (480, 640) bool over the current
    image, ``truth_disappeared`` (480, 640) bool over the reference image (rule: module
    docstring).  ``footprint_reference``/``footprint_current``: (480, 640) bool, the frame's
    cropped region (valid pixels plus enclosed dropout holes).  ``margin_mm`` /
    ``min_region_px``: the truth rule's parameters.  ``reference_paths`` /
    ``current_paths``: the depth PNG, as a 1-tuple.  Like :class:`sim_fixtures.Scene`, it offers
    ``reference_frames()`` / ``current_frames()``.
    """

    name: str
    description: str
    reference_name: str
    current_name: str
    folder: Path
    intrinsics: Intrinsics
    margin_mm: int
    min_region_px: int
    reference: np.ndarray
    current: np.ndarray
    reference_labels: np.ndarray
    current_labels: np.ndarray
    truth_appeared: np.ndarray
    truth_disappeared: np.ndarray
    footprint_reference: np.ndarray
    footprint_current: np.ndarray
    reference_paths: tuple[Path, ...]
    current_paths: tuple[Path, ...]

    @property
    def change(self) -> str:
        """What changes, as the data README describes it."""
        return self.description

    @property
    def has_change(self) -> bool:
        """Every real pair has a change (there is no unchanged pair in the data)."""
        return True

    @property
    def crop_mismatch(self) -> np.ndarray:
        """(480, 640) bool: inside one frame's footprint but outside the other's (the crop
        differs there: neither appeared nor disappeared, whatever a detector sees)."""
        return self.footprint_reference ^ self.footprint_current

    def reference_frames(self) -> list[np.ndarray]:
        """[reference]: a list of one (480, 640) uint16 mm frame, like ``Scene``."""
        return [self.reference]

    def current_frames(self) -> list[np.ndarray]:
        """[current]: a list of one (480, 640) uint16 mm frame, like ``Scene``."""
        return [self.current]


def tabletop_pairs() -> list[str]:
    """Names of the 9 pairs, in the data README's order (``"<reference>-<current>"``)."""
    return list(PAIRS)


def footprint(depth: np.ndarray) -> np.ndarray:
    """(H, W) bool: valid pixels of ``depth`` ((H, W), 0 = none) with enclosed holes filled;
    outside it the frame was cropped (or the hole reaches the crop)."""
    return ndimage.binary_fill_holes(depth > 0)


def fill_dropouts(depth: np.ndarray, region: np.ndarray | None = None) -> np.ndarray:
    """``depth`` ((H, W) uint16 mm) with its holes inside ``region`` ((H, W) bool; default its
    :func:`footprint`) filled from their edge inward, ring by ring, each pixel taking the
    nearest (smallest) depth among its 3x3 neighbours already known.  Outside ``region`` stays
    0.  Returns (H, W) int32 mm."""
    depth = np.asarray(depth)
    if region is None:
        region = footprint(depth)
    big = np.iinfo(np.int32).max
    filled = np.where(depth > 0, depth.astype(np.int32), big)
    todo = region & (depth == 0)
    while todo.any():
        grown = ndimage.grey_erosion(filled, size=3, mode="constant", cval=big)
        reached = todo & (grown < big)
        if not reached.any():  # a hole with no valid pixel at all in its region
            break
        filled[reached] = grown[reached]
        todo &= ~reached
    filled[(filled == big) | ~region] = 0
    return filled


def _seen_through(depth: np.ndarray, labels: np.ndarray, other: np.ndarray,
                  margin_mm: float) -> np.ndarray:
    """Object pixels of (depth, labels) where ``other`` (same scene, other epoch) sees farther
    than depth + margin, with other's crop excluded and its dropouts filled."""
    other_filled = fill_dropouts(other)  # 0 outside other's footprint: never "farther"
    d = depth.astype(np.int32)
    return (labels >= OBJECT_LABEL_MIN) & (d > 0) & (other_filled > d + margin_mm)


def drop_specks(mask: np.ndarray, min_px: int = MIN_REGION_PX) -> np.ndarray:
    """``mask`` ((H, W) bool) without its 8-connected components of fewer than ``min_px``
    pixels."""
    regions, _ = ndimage.label(mask, structure=np.ones((3, 3), bool))
    sizes = np.bincount(regions.ravel())
    keep = sizes >= min_px
    keep[0] = False
    return keep[regions]


def tabletop_truth(reference: np.ndarray, reference_labels: np.ndarray, current: np.ndarray,
                   current_labels: np.ndarray, margin_mm: float = TRUTH_MARGIN_MM,
                   min_region_px: int = MIN_REGION_PX) -> tuple[np.ndarray, np.ndarray]:
    """(appeared, disappeared): (H, W) bool over the current and the reference image.

    ``reference``/``current``: (H, W) uint16 depth, mm, 0 = none; ``*_labels``: (H, W) integer
    labels (>= 20 object).  ``min_region_px``: smaller 8-connected specks are dropped (0 or 1
    keeps them).  Rule and margin: module docstring.
    """
    shapes = {np.shape(a) for a in (reference, reference_labels, current, current_labels)}
    if len(shapes) != 1 or len(next(iter(shapes))) != 2:
        raise ValueError(f"depth and label images must be one (H, W) shape, got {sorted(shapes)}")
    appeared = _seen_through(current, current_labels, reference, margin_mm)
    disappeared = _seen_through(reference, reference_labels, current, margin_mm)
    return drop_specks(appeared, min_region_px), drop_specks(disappeared, min_region_px)


def changed_objects(labels: np.ndarray, truth: np.ndarray, edge_px: int = OBJECT_EDGE_PX,
                    min_px: int = MIN_REGION_PX) -> np.ndarray:
    """(H, W) bool: every pixel of each object that changed, all its parts.

    ``labels``: (H, W) integer labels of one frame (object id = label // 10, labels >=
    :data:`OBJECT_LABEL_MIN`); ``truth``: (H, W) bool, that frame's truth.  An object changed
    when at least ``min_px`` of its truth pixels lie more than ``edge_px`` pixels inside it; a
    few truth pixels along its edge (a neighbour's change spilling over, depth-edge flicker) do
    not make it one.  The simulated scenes' truth is whole objects; this is the same for the
    real pairs, whose geometric truth leaves out what a moved object covers in both frames.
    """
    objects = np.where(labels >= OBJECT_LABEL_MIN, labels // 10, 0)
    out = np.zeros(objects.shape, bool)
    for obj in np.unique(objects[truth & (objects > 0)]):
        mask = objects == obj
        # (iterations=0 would erode until nothing changes)
        core = ndimage.binary_erosion(mask, iterations=edge_px) if edge_px > 0 else mask
        if int((core & truth).sum()) >= min_px:
            out |= mask
    return out


def seen_from(depth: np.ndarray, intrinsics: Intrinsics, T_new_from_old: np.ndarray
              ) -> np.ndarray:
    """(H, W) uint16 mm: ``depth`` (H, W) uint16 mm, 0 = no reading, as a camera moved by
    ``T_new_from_old`` (4, 4, metres, maps the old camera's points into the new one's frame)
    would read it: every reading back-projected, moved and drawn into a z-buffer (the
    nearest wins).  What the old camera did not see stays a hole, so a table top seen
    from a displaced robot (bench/bench_registration.py ``--tabletop``, the registration
    tests) has the holes a real revisit would fill."""
    v, u = np.nonzero(depth)
    z = depth[v, u] / 1000.0
    K = intrinsics
    p = np.stack([(u - K.cx) * z / K.fx, (v - K.cy) * z / K.fy, z], axis=1)
    p = p @ T_new_from_old[:3, :3].T + T_new_from_old[:3, 3]
    p = p[p[:, 2] > 0.1]
    u = np.floor(K.fx * p[:, 0] / p[:, 2] + K.cx + 0.5).astype(np.int64)
    v = np.floor(K.fy * p[:, 1] / p[:, 2] + K.cy + 0.5).astype(np.int64)
    inside = (u >= 0) & (v >= 0) & (u < depth.shape[1]) & (v < depth.shape[0])
    out = np.full(depth.shape, np.iinfo(np.int64).max)
    np.minimum.at(out, (v[inside], u[inside]), np.round(p[inside, 2] * 1000).astype(np.int64))
    out[out == np.iinfo(np.int64).max] = 0
    return out.astype(np.uint16)


def _read(path: Path, reader) -> np.ndarray:
    if not path.is_file():
        raise TabletopDataMissing(f"{path}: missing (expected beside the others in "
                                  f"{path.parent}; see the data README)")
    image = reader(path)
    if image.shape != SHAPE or image.dtype != np.uint16:
        raise ValueError(f"{path}: expected a {SHAPE} uint16 image, got {image.shape} "
                         f"{image.dtype}")
    return image


def load_tabletop_pair(name: str, data_dir: str | Path | None = None) -> TabletopPair:
    """The pair ``name`` (one of :func:`tabletop_pairs`) with its truth.

    ``data_dir``: the osd-tabletop folder (holding ``derived/``); default
    :data:`DEFAULT_DATA_DIR`.  Raises :class:`~sim_fixtures.UnknownScene` (a KeyError) for an
    unknown name, listing the known ones, and :class:`TabletopDataMissing` (a
    FileNotFoundError) when the folder or one of its images is missing.
    """
    if name not in PAIRS:
        raise UnknownScene(f"no table-top pair {name!r}; known pairs: {', '.join(PAIRS)}")
    from hw.imagefile import read_image
    from hw.images import read_depth_image

    folder = Path(DEFAULT_DATA_DIR if data_dir is None else data_dir)
    derived = folder / "derived"
    if not derived.is_dir():
        raise TabletopDataMissing(
            f"table-top data not found: {derived} is not a folder (the real pairs live in "
            f"../shared/data/osd-tabletop beside the project's checkout, not in the repository; "
            f"pass data_dir= to read them elsewhere)")
    ref_name, cur_name, description = PAIRS[name]
    ref_path = derived / f"{ref_name}_depth_mm.png"
    cur_path = derived / f"{cur_name}_depth_mm.png"
    reference = _read(ref_path, read_depth_image)
    current = _read(cur_path, read_depth_image)
    reference_labels = _read(derived / f"{ref_name}_label.png", read_image)
    current_labels = _read(derived / f"{cur_name}_label.png", read_image)
    appeared, disappeared = tabletop_truth(reference, reference_labels, current, current_labels)
    return TabletopPair(
        name=name,
        description=description,
        reference_name=ref_name,
        current_name=cur_name,
        folder=folder,
        intrinsics=Intrinsics.openni_default(),
        margin_mm=TRUTH_MARGIN_MM,
        min_region_px=MIN_REGION_PX,
        reference=reference,
        current=current,
        reference_labels=reference_labels,
        current_labels=current_labels,
        truth_appeared=appeared,
        truth_disappeared=disappeared,
        footprint_reference=footprint(reference),
        footprint_current=footprint(current),
        reference_paths=(ref_path,),
        current_paths=(cur_path,),
    )
