"""Synthetic Kinect-like depth scenes with known truth, for tests and benchmarks.

    from sim_fixtures import load_scene, scene_names
    scene = load_scene("office_box_added")
    frames = scene.current_frames()          # list of (H, W) uint16 mm arrays
    scene.truth_appeared                     # (H, W) bool, current image
    open_depth(scene.uri("reference"))       # the same frames through hw's images backend

The files live in ``sim_fixtures/scenes/<name>/`` (see ``make_fixtures.py`` for the layout);
``render.py``, ``noise.py`` and ``scenes.py`` are how they were made.  ``DEMO_FRAME`` is the
one-frame demo/benchmark image.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np

from hw.depth import Intrinsics

__all__ = ["Scene", "load_scene", "scene_names", "SCENES_DIR", "DEMO_FRAME", "UnknownScene"]

ROOT = Path(__file__).resolve().parent
SCENES_DIR = ROOT / "scenes"
#: (480, 640) uint16 mm: a furnished room with Kinect noise (``robot-change demo`` / ``bench``).
DEMO_FRAME = ROOT / "frames" / "room_vga.png"


class UnknownScene(KeyError):
    """No stored scene by that name; the message lists the ones there are."""

    def __str__(self) -> str:  # KeyError would quote the message
        return str(self.args[0])


def _read_png(path: Path) -> np.ndarray:
    from hw.png import read_png

    return read_png(path)


@dataclasses.dataclass(frozen=True, eq=False)
class Scene:
    """One stored scene.

    ``reference_paths``/``current_paths``: the 16-bit PNG frames ((H, W) uint16 mm, 0 = no
    reading), in order.  ``truth_appeared`` (H, W) bool over the current image,
    ``truth_disappeared`` (H, W) bool over the reference image.  ``meta``: the parsed
    scene.json (noise model, seed, poses, ``changes`` with centroids and extents in the camera
    frame, metres).
    """

    name: str
    split: str
    folder: Path
    meta: dict
    intrinsics: Intrinsics
    reference_paths: tuple[Path, ...]
    current_paths: tuple[Path, ...]
    truth_appeared: np.ndarray
    truth_disappeared: np.ndarray

    @property
    def change(self) -> str:
        """'added', 'removed', 'moved', 'two', 'small', 'none' or 'none_jitter'."""
        return self.meta["change"]

    @property
    def changes(self) -> list[dict]:
        """The changed objects (kind, object, before/after geometry); empty if none."""
        return self.meta["changes"]

    @property
    def has_change(self) -> bool:
        return bool(self.meta["changes"])

    def reference_frames(self) -> list[np.ndarray]:
        """The reference recording: list of (H, W) uint16 mm."""
        return [_read_png(p) for p in self.reference_paths]

    def current_frames(self) -> list[np.ndarray]:
        """The current recording: list of (H, W) uint16 mm."""
        return [_read_png(p) for p in self.current_paths]

    def object_ids(self, epoch: str) -> np.ndarray:
        """(H, W) uint8 object ids of the ideal render of ``epoch`` ('reference' or 'current');
        ids are listed in ``meta['objects']``, 0 = nothing."""
        if epoch not in ("reference", "current"):
            raise ValueError(f"epoch {epoch!r}: expected 'reference' or 'current'")
        return _read_png(self.folder / f"ids_{epoch}.png")

    def uri(self, epoch: str) -> str:
        """``images:`` URI of an epoch's frame folder, for ``hw.depth.open_depth``."""
        if epoch not in ("reference", "current"):
            raise ValueError(f"epoch {epoch!r}: expected 'reference' or 'current'")
        return f"images:{self.folder / epoch}/"


def _stored() -> dict[str, dict]:
    out = {}
    for path in sorted(SCENES_DIR.glob("*/scene.json")):
        out[path.parent.name] = json.loads(path.read_text())
    return out


def scene_names(split: str | None = None) -> list[str]:
    """Names of the stored scenes (sorted), all or those of ``split`` ('dev' or 'holdout')."""
    if split not in (None, "dev", "holdout"):
        raise ValueError(f"split {split!r}: expected None, 'dev' or 'holdout'")
    return [n for n, m in _stored().items() if split is None or m["split"] == split]


def load_scene(name: str) -> Scene:
    """The stored scene ``name``; :class:`UnknownScene` (a KeyError) lists the known names."""
    folder = SCENES_DIR / name
    meta_path = folder / "scene.json"
    if not name or "/" in name or not meta_path.is_file():
        known = ", ".join(scene_names()) or "none (run python -m sim_fixtures.make_fixtures)"
        raise UnknownScene(f"no stored scene {name!r} in {SCENES_DIR}; known scenes: {known}")
    meta = json.loads(meta_path.read_text())
    files = meta["files"]
    i = meta["intrinsics"]
    return Scene(
        name=meta["name"],
        split=meta["split"],
        folder=folder,
        meta=meta,
        intrinsics=Intrinsics(i["width"], i["height"], i["fx"], i["fy"], i["cx"], i["cy"]),
        reference_paths=tuple(folder / f for f in files["reference"]),
        current_paths=tuple(folder / f for f in files["current"]),
        truth_appeared=_read_png(folder / files["truth_appeared"]) > 0,
        truth_disappeared=_read_png(folder / files["truth_disappeared"]) > 0,
    )
