"""Depth images on disk as a depth source: a 16-bit PNG/TIFF file, or a folder of them.

``open_depth("images:tum/depth?scale=5000&rate=30&loop=1")`` reaches :func:`open_images`.
Frames come in natural name order (``frame_2`` before ``frame_10``); of a folder that mixes
depth images with others, those named depth (:func:`depth_named`; ``pattern=`` picks
otherwise).  One file is decoded per :meth:`ImageFolderSource.read` (:mod:`hw.imagefile`,
Pillow), converted to uint16 millimetres.
"""

from __future__ import annotations

import datetime
import decimal
import fnmatch
import re
from pathlib import Path
from typing import Any

import numpy as np

from hw.depth import IMAGE_SUFFIXES, DepthFrame, DepthSource, Intrinsics
from hw.errors import DepthFileError, DeviceError, FrameError, NotDepthImageError, UriError
from hw.imagefile import decode_image, read_file
from hw.options import Pacer, flag, intrinsics_option, positive

#: Frame period (µs) assumed when file names carry no time: 30 Hz, as OpenNI cameras.
DEFAULT_PERIOD_US = 1_000_000 // 30
_OPTIONS = ("scale", "rate", "loop", "intrinsics", "pattern")
# TUM RGB-D: "<seconds>.<fraction>", e.g. 1305031102.160407
_SECONDS_STEM = re.compile(r"\d+\.\d+")
# PCL's image grabber: "frame_20121214T142255.814212_depth" (local time, read as UTC)
_DATETIME_STEM = re.compile(r"(\d{8}T\d{6})(\.\d{1,6})?")


def read_depth_image(path: str | Path, scale: float = 1000.0) -> np.ndarray:
    """Read a 16-bit PNG or TIFF depth image as (H, W) uint16 millimetres.

    ``scale``: raw units per metre in the file (1000 = millimetres, the default; 5000 = TUM
    RGB-D).  Values are converted with rounding (half up) and saturate at 65535; 0 (no
    reading) stays 0.  The format is told from the file's first bytes, not its name.  Raises
    :class:`DepthFileError` for a missing, corrupt or unsupported file, including an 8-bit
    image (not depth).
    """
    name = str(path)
    raw = decode_image(read_file(path), name)
    if raw.dtype != np.uint16:
        raise NotDepthImageError(f"{name}: 8-bit grayscale image is not a depth image; depth "
                                 "images are 16-bit (millimetres, or raw units with a scale)")
    return to_millimetres(raw, scale)


#: Depths (mm) a depth camera reads: a first image whose readings mostly lie outside is in other
#: units than the scale says.
PLAUSIBLE_DEPTH_MM = (300, 10_000)


def check_depth_scale(depth: np.ndarray, scale: float, name: str) -> None:
    """Raise :class:`DepthFileError` naming ``?scale=`` when most readings of ``depth`` (H, W)
    uint16 mm lie outside :data:`PLAUSIBLE_DEPTH_MM` (a TUM image, 5000 units per metre, read
    as millimetres lands at 5-30 m; one in metres x 100 at 1-5 cm)."""
    valid = depth[depth > 0]
    if valid.size < 100:
        return  # nothing to judge by (a covered lens is the check's business)
    low, high = PLAUSIBLE_DEPTH_MM
    outside = np.count_nonzero((valid < low) | (valid > high))
    if 2 * outside > valid.size:
        median = float(np.median(valid)) / 1000.0
        raise DepthFileError(
            f"{name}: at scale={scale:g} units per metre the median reading is {median:.2f} m "
            f"and {100 * outside // valid.size} % lie outside the {low / 1000:g}-"
            f"{high / 1000:g} m a depth camera reads: the image holds other units; give them "
            "with ?scale= (e.g. images:DIR?scale=5000 for TUM RGB-D depth), or it holds no "
            "depth at all (labels, a mask)")


def to_millimetres(raw: np.ndarray, scale: float) -> np.ndarray:
    """(H, W) uint16 raw units, ``scale`` of them per metre -> (H, W) uint16 millimetres
    (rounded half up, saturated at 65535; 0 stays 0).  Returns ``raw`` itself when scale is
    1000."""
    if scale == 1000.0:
        return raw
    millimetres = np.floor(raw * 1000.0 / scale + 0.5)
    return np.minimum(millimetres, 65535.0).astype(np.uint16)


def natural_key(name: str) -> tuple:
    """Sort key putting ``frame_2`` before ``frame_10`` (digit runs compare as numbers,
    letters case-insensitively; the exact name breaks ties)."""
    parts = re.split(r"(\d+)", name)
    return tuple(int(part) if index % 2 else part.lower()
                 for index, part in enumerate(parts)), name


def stem_timestamp_us(stem: str) -> int | None:
    """The time a file name gives, in µs, or None.

    ``1305031102.160407`` (TUM: seconds with a fraction) -> 1305031102160407;
    ``frame_20121214T142255.814212_depth`` (PCL grabber: date and time, taken as UTC) -> µs
    since 1970.  A plain number such as ``000123`` is a frame number, not a time: None.
    """
    if _SECONDS_STEM.fullmatch(stem):
        seconds = decimal.Decimal(stem)
        return int((seconds * 1_000_000).to_integral_value(decimal.ROUND_HALF_UP))
    match = _DATETIME_STEM.search(stem)
    if match:
        try:
            moment = datetime.datetime.strptime(match.group(1), "%Y%m%dT%H%M%S")
        except ValueError:
            return None
        moment = moment.replace(tzinfo=datetime.UTC)
        fraction = match.group(2) or ".0"
        micros = int(fraction[1:].ljust(6, "0"))
        return int(moment.timestamp()) * 1_000_000 + micros
    return None


def list_images(folder: Path, pattern: str | None = None,
                suffixes: tuple[str, ...] = IMAGE_SUFFIXES) -> list[Path]:
    """The depth image files in ``folder`` (``*.png``, ``*.tif``, ``*.tiff``, or the given
    ``suffixes``; any case, hidden files skipped, optionally only names matching the glob
    ``pattern``), in natural name order.  Raises :class:`DepthFileError` when there are none."""
    try:
        entries = list(folder.iterdir())
    except OSError as exc:
        raise DepthFileError(f"{folder}: cannot list the folder ({exc.strerror or exc})") from None
    files = [path for path in entries
             if path.suffix.lower() in suffixes and not path.name.startswith(".")
             and (pattern is None or fnmatch.fnmatch(path.name, pattern)) and path.is_file()]
    if not files:
        looked_for = ", ".join(f"*{suffix}" for suffix in suffixes)
        if pattern is not None:
            looked_for += f" matching {pattern!r}"
        hints = []
        if ".pcd" not in suffixes and any(path.suffix.lower() == ".pcd" for path in entries):
            hints.append(f"it holds .pcd clouds: read them with pcd:{folder}")
        hints += [f"its folder {path.name!r} may hold them" for path in entries
                  if path.is_dir() and "depth" in path.name.lower()]
        raise DepthFileError(f"{folder}: no depth images in this folder (looked for "
                             f"{looked_for})" + "".join(f"; {hint}" for hint in hints))
    return sorted(files, key=lambda path: natural_key(path.name))


def depth_named(files: list[Path]) -> list[Path]:
    """The ones of ``files`` named depth (any case) when some are and some are not: a
    dataset's folder of depth frames beside colour frames or labels (SUN3D and 7-Scenes
    ``frame-N.depth.png`` and ``.color.png``, PCL's grabber ``*_depth.tiff`` and ``*_rgb.tiff``,
    OSD's ``*_depth_mm.png`` and ``*_label.png``); all of them otherwise."""
    depth = [path for path in files if "depth" in path.name.lower()]
    return depth or files


class ImageFolderSource(DepthSource):
    """Depth images delivered as frames, like a camera.

    ``files``: the images in delivery order; ``scale``: raw units per metre; ``rate``: frames
    per second to pace delivery at (None: as fast as they are read); ``loop``: start again
    after the last file; ``intrinsics``: an :class:`Intrinsics` for the images' size,
    ``"fx,fy,cx,cy"`` text, or None for :meth:`Intrinsics.openni_default`.

    Frame ``index`` counts delivered positions across loops.  ``timestamp_us`` comes from the
    file names when every name holds a time (see :func:`stem_timestamp_us`; later loops are
    shifted to keep time increasing), else ``index`` / 30 s.  Every file must have the size of
    the first (:class:`FrameError` otherwise).  A file that fails to decode raises
    :class:`DepthFileError` and counts as dropped; the next read moves on to the next file.
    """

    def __init__(self, files: list[Path], *, scale: float = 1000.0, rate: float | None = None,
                 loop: bool = False, intrinsics: Intrinsics | str | None = None) -> None:
        super().__init__()
        if not files:
            raise DepthFileError("an images source needs at least one file")
        self.files = list(files)
        self.scale = scale
        self.rate = rate
        self._pacer = Pacer(rate)
        self.loop = loop
        self._given_intrinsics = intrinsics
        self._intrinsics: Intrinsics | None = None
        self._first: np.ndarray | None = None  # first image, decoded early for its size
        self._position = 0
        self._open = False
        stamps = [stem_timestamp_us(path.stem) for path in self.files]
        if all(stamp is not None for stamp in stamps):
            order = sorted(range(len(self.files)), key=lambda i: (stamps[i], i))
            self.files = [self.files[i] for i in order]
            self._stamps: list[int] | None = [stamps[i] for i in order]  # type: ignore[misc]
        else:
            self._stamps = None

    def __repr__(self) -> str:
        where = self.files[0] if len(self.files) == 1 else self.files[0].parent
        return f"<ImageFolderSource {where} ({len(self.files)} files)>"

    @property
    def intrinsics(self) -> Intrinsics:
        """Intrinsics of the frames (decodes the first image to learn the size, if needed)."""
        if self._intrinsics is None:
            self._first = self._decode(self.files[0])
            height, width = self._first.shape
            self._intrinsics = self._make_intrinsics(width, height)
        return self._intrinsics

    def _make_intrinsics(self, width: int, height: int) -> Intrinsics:
        given = self._given_intrinsics
        if given is None:
            return Intrinsics.openni_default(width, height)
        if isinstance(given, str):
            return Intrinsics.parse(given, width, height)
        if (given.width, given.height) != (width, height):
            raise FrameError(
                f"{self.files[0]}: the images are {width}x{height} but the intrinsics given "
                f"are for {given.width}x{given.height}; pass intrinsics for {width}x{height} "
                "(Intrinsics.scaled)")
        return given

    def open(self) -> None:
        """Start at the first file (again, after :meth:`close`); learns the image size."""
        if self._open:
            return
        self._position = 0
        self._pacer.reset()
        self.intrinsics  # noqa: B018 - decode the first file: size and intrinsics errors now
        if self._first is not None:
            check_depth_scale(self._first, self.scale, str(self.files[0]))
        self._open = True

    def close(self) -> None:
        """Stop; a later :meth:`open` starts from the first file."""
        self._open = False
        self._first = None

    def read(self, timeout: float | None = 1.0) -> DepthFrame | None:
        """The next frame; ``None`` after the last file when not looping.

        With a ``rate``, waits until the frame is due; if that is more than ``timeout`` seconds
        away, waits ``timeout`` and raises :class:`FrameTimeout` (the frame stays next).
        """
        if not self._open:
            raise DeviceError(f"{self!r} is not open: call open() or use it in a 'with' block")
        count = len(self.files)
        if self._position >= count and not self.loop:
            return None
        self._pacer.wait(timeout, repr(self))
        index = self._position
        self._position += 1
        lap, slot = divmod(index, count)
        path = self.files[slot]
        if index == 0 and self._first is not None:
            depth, self._first = self._first, None
        else:
            try:
                depth = self._decode(path)
            except DepthFileError:
                self.stats.dropped += 1
                raise
        intrinsics = self.intrinsics
        if depth.shape != (intrinsics.height, intrinsics.width):
            self.stats.dropped += 1
            raise FrameError(
                f"{path}: is {depth.shape[1]}x{depth.shape[0]} but {self.files[0].name} is "
                f"{intrinsics.width}x{intrinsics.height}; every image in a folder must have "
                "the same size")
        frame = DepthFrame(depth, self._timestamp_us(lap, slot, index), index, intrinsics)
        self.stats.delivered += 1
        return frame

    def _decode(self, path: Path) -> np.ndarray:
        try:
            return read_depth_image(path, self.scale)
        except NotDepthImageError as exc:
            if len(self.files) == 1:
                raise
            raise NotDepthImageError(
                f"{exc}; the folder holds other images beside the depth ones: pick those with "
                "?pattern= (e.g. images:DIR?pattern=*_depth.png)") from None

    def _timestamp_us(self, lap: int, slot: int, index: int) -> int:
        if self._stamps is None:
            return index * 1_000_000 // 30
        stamps = self._stamps
        span = stamps[-1] - stamps[0]
        period = span // (len(stamps) - 1) if len(stamps) > 1 else DEFAULT_PERIOD_US
        return stamps[slot] + lap * (span + max(period, 1))

def open_images(target: str, *, scale: Any = 1000.0, rate: Any = None, loop: Any = False,
                intrinsics: Any = None, pattern: Any = None, **unknown: Any) -> ImageFolderSource:
    """The ``images:`` backend of :func:`hw.depth.open_depth`.

    ``target``: an image file or a folder of them.  Options (Python values, or the strings of
    a URI query): ``scale`` raw units per metre (1000 = mm, 5000 = TUM); ``rate`` Hz to pace
    delivery at; ``loop`` (1/0, true/false, yes/no); ``intrinsics`` an :class:`Intrinsics` or
    ``"fx,fy,cx,cy"``; ``pattern`` a glob the file names must match (e.g. ``*_depth.tiff``;
    without one, a folder's files named depth when some are: :func:`depth_named`).
    Raises :class:`UriError` for bad or unknown options and :class:`DepthFileError` when the
    target is missing or holds no images.  The source is returned unopened.
    """
    if unknown:
        raise UriError(f"images option(s) {', '.join(sorted(unknown))} unknown; the images "
                       f"backend takes {', '.join(_OPTIONS)}")
    scale_value = positive("images", "scale", scale, "raw units per metre: 1000 for "
                           "millimetres, 5000 for TUM RGB-D")
    rate_value = None if rate is None or rate == "" else positive(
        "images", "rate", rate, "frames per second; leave it out to read as fast as possible")
    loop_value = flag("images", "loop", loop)
    intrinsics = intrinsics_option("images", intrinsics)
    if pattern is not None and not isinstance(pattern, str):
        raise UriError(f"images option pattern={pattern!r}: expected a glob such as "
                       "'*_depth.png'")

    path = Path(target)
    if path.is_dir():
        files = list_images(path, pattern or None)
        if not pattern:
            files = depth_named(files)
    elif path.is_file():
        files = [path]
    else:
        raise DepthFileError(f"{target}: no such file or folder (expected a depth image or a "
                             "folder of them)")
    return ImageFolderSource(files, scale=scale_value, rate=rate_value, loop=loop_value,
                             intrinsics=intrinsics)

