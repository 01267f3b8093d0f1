"""Synthetic Kinect-like depth scenes with known truth, for tests and benchmarks.

    from sim_fixtures import load_scene, scene_names
    scene = load_scene("office_box_added")
    frames = scene.current_frames()          # list of (H, W) uint16 mm arrays
    scene.truth_appeared                     # (H, W) bool, current image
    open_depth(scene.uri("reference"))       # the recording through the real OpenNI2 player
    open_depth(scene.uri("reference", "images"))   # the same frames as a folder of 16-bit PNGs

The files live in ``sim_fixtures/scenes/<name>/`` (see ``make_fixtures.py`` for the layout);
``render.py``, ``noise.py`` and ``scenes.py`` are how they were made.  ``DEMO_FRAME`` is the
one-frame demo/benchmark image.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import shutil
import tempfile
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
    from hw.imagefile import read_image

    return read_image(path)


#: scene.json layout this loader reads (``make_fixtures.FORMAT_VERSION``).
FORMAT_VERSION = 2
EPOCHS = ("reference", "current")
#: Where :meth:`Scene.uri` writes PNG copies of a recording when none are stored.
IMAGE_CACHE = Path(tempfile.gettempdir()) / "robot_change-sim_fixtures"


@dataclasses.dataclass(frozen=True, eq=False)
class Scene:
    """One stored scene.

    ``reference_oni``/``current_oni``: the recordings (OpenNI2 ``.oni``, (H, W) uint16 mm,
    0 = no reading, 30 fps).  ``reference_pngs``/``current_pngs``: per-frame 16-bit PNGs when
    the fixtures were written with ``--png``, else empty.  ``truth_appeared`` (H, W) bool over
    the current image, ``truth_disappeared`` (H, W) bool over the reference image.
    ``observed_reference`` (H, W) bool: reference pixels the current camera could see (inside
    its image and range, not hidden); ``observed_current`` likewise.  ``meta``:
    the parsed scene.json (noise model, seed, poses, ``changes`` with centroids and extents in
    the camera frame, metres; ``recordings`` with each file's codec and frame count).
    """

    name: str
    split: str
    folder: Path
    meta: dict
    intrinsics: Intrinsics
    reference_oni: Path
    current_oni: Path
    reference_pngs: tuple[Path, ...]
    current_pngs: tuple[Path, ...]
    truth_appeared: np.ndarray
    truth_disappeared: np.ndarray
    observed_reference: np.ndarray
    observed_current: np.ndarray

    @property
    def change(self) -> str:
        """'added', 'removed', 'moved', 'two', 'small', 'none', 'none_jitter' or
        'not_at_station' (the current view is of another place)."""
        return self.meta["change"]

    @property
    def T_ref_from_cur(self) -> np.ndarray:
        """(4, 4) float64: the true transform from the current camera frame to the reference
        camera frame (the registration's truth)."""
        return np.array(self.meta["T_ref_from_cur"], dtype=np.float64)

    @property
    def revisits(self) -> str | None:
        """The scene whose reference this one shares (a revisit with a pose offset), or None."""
        return self.meta.get("reference_from")

    @property
    def changes(self) -> list[dict]:
        """The changed objects (kind, object, before/after geometry); empty if none."""
        return self.meta["changes"]

    @property
    def has_change(self) -> bool:
        return bool(self.meta["changes"])

    def recording(self, epoch: str) -> Path:
        """The ``.oni`` file of ``epoch`` ('reference' or 'current')."""
        return self.reference_oni if _check_epoch(epoch) == "reference" else self.current_oni

    def frames(self, epoch: str) -> list[np.ndarray]:
        """The frames of ``epoch``: list of (H, W) uint16 mm, decoded from its .oni by
        ``hw.oni.read_oni_frames`` (no native library; ~5 ms a frame)."""
        from hw.oni import read_oni_frames

        return [f.depth for f in read_oni_frames(self.recording(epoch))]

    def reference_frames(self) -> list[np.ndarray]:
        """The reference recording: list of (H, W) uint16 mm."""
        return self.frames("reference")

    def current_frames(self) -> list[np.ndarray]:
        """The current recording: list of (H, W) uint16 mm."""
        return self.frames("current")

    def object_ids(self, epoch: str) -> np.ndarray:
        """(H, W) uint8 object ids of the ideal render of ``epoch`` ('reference' or 'current');
        ids are listed in ``meta['objects']``, 0 = nothing."""
        return _read_png(self.folder / f"ids_{_check_epoch(epoch)}.png")

    def uri(self, epoch: str, kind: str = "oni") -> str:
        """A ``hw.depth.open_depth`` URI of ``epoch``'s frames.

        ``kind="oni"``: ``oni:<scene>/<epoch>.oni``, played by the real OpenNI2 library.
        ``kind="images"``: ``images:<folder>/`` of 16-bit PNGs -- the stored ones when written
        with ``--png``, else copies decoded from the .oni into :data:`IMAGE_CACHE` (once per
        file content; the folder name holds the recording's hash, so it is never stale).
        """
        path = self.recording(epoch)
        if kind == "oni":
            return f"oni:{path}"
        if kind != "images":
            raise ValueError(f"kind {kind!r}: expected 'oni' or 'images'")
        pngs = self.reference_pngs if epoch == "reference" else self.current_pngs
        if pngs:
            return f"images:{pngs[0].parent}/"
        return f"images:{_png_copy(self, epoch)}/"


def _check_epoch(epoch: str) -> str:
    if epoch not in EPOCHS:
        raise ValueError(f"epoch {epoch!r}: expected 'reference' or 'current'")
    return epoch


def _png_copy(scene: Scene, epoch: str) -> Path:
    """A folder of ``000.png ...`` holding the frames of ``scene``'s ``epoch`` recording."""
    from hw.imagefile import write_png

    path = scene.recording(epoch)
    digest = hashlib.sha256(path.read_bytes()).hexdigest()[:16]
    folder = IMAGE_CACHE / f"{scene.name}-{epoch}-{digest}"
    if folder.is_dir():
        return folder
    IMAGE_CACHE.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{folder.name}.", dir=IMAGE_CACHE))
    try:
        for k, frame in enumerate(scene.frames(epoch)):
            write_png(tmp / f"{k:03d}.png", frame, level=1)
        os.rename(tmp, folder)
    except OSError:
        if not folder.is_dir():  # not a concurrent writer that got there first
            raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return folder


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
    if meta.get("format_version") != FORMAT_VERSION:
        raise ValueError(
            f"{meta_path} has format_version {meta.get('format_version')}, this loader reads "
            f"{FORMAT_VERSION}: regenerate with python -m sim_fixtures.make_fixtures"
        )
    files = meta["files"]
    i = meta["intrinsics"]
    return Scene(
        name=meta["name"],
        split=meta["split"],
        folder=folder,
        meta=meta,
        intrinsics=Intrinsics(i["width"], i["height"], i["fx"], i["fy"], i["cx"], i["cy"]),
        reference_oni=(folder / files["reference"]).resolve(),
        current_oni=folder / files["current"],
        reference_pngs=tuple(folder / f for f in files.get("reference_png", ())),
        current_pngs=tuple(folder / f for f in files.get("current_png", ())),
        truth_appeared=_read_png(folder / files["truth_appeared"]) > 0,
        truth_disappeared=_read_png(folder / files["truth_disappeared"]) > 0,
        observed_reference=_read_png(folder / files["observed_reference"]) > 0,
        observed_current=_read_png(folder / files["observed_current"]) > 0,
    )
