"""Depth frames, the DepthSource interface, and ``open_depth(uri)``.

Every depth backend (a live OpenNI2 or RealSense camera, an ``.oni``, RealSense or Azure Kinect
recording, a folder of 16-bit images, a ROS bag's depth topic, organized PCD clouds) delivers
the same thing: :class:`DepthFrame` objects through the :class:`DepthSource` interface.  The
rest of the project never knows which backend it is reading from.

URIs (python-can / pyserial style; the backend module is imported only when used)::

    openni2://                  first OpenNI2 camera (Kinect / PrimeSense / Xtion)
    openni2://<serial-or-uri>   a given camera
    oni:path/to/file.oni        an OpenNI2 recording; a bare path ending in .oni works too
    realsense://                first Intel RealSense camera (pyrealsense2)
    realsense://<serial>?resolution=848x480&fps=30&preset=high_accuracy
                                a given one, in a given mode
    realsense:path/to/run.db3   a RealSense recording (.db3, or .bag of librealsense < 2.59)
                                played through librealsense; a bare .db3 path reads it through
                                the bag backend instead (the same frames)
    images:path/to/folder/      16-bit PNG/TIFF depth images in name order
    images:path/to/frame.png    a single image; a bare path to an image or a folder works too
    rosbag:path/to/bag?topic=/camera/depth/image_raw
                                a depth topic of a ROS 1 .bag or a ROS 2 bag (folder, .db3 or
                                .mcap); a bare .bag / .db3 / .mcap path or a folder holding
                                metadata.yaml works too
    pcd:path/to/cloud.pcd       an organized PCD (or a folder of them): z -> depth; a bare
                                .pcd path works too
    mkv:path/to/recording.mkv   an Azure Kinect recording (k4arecorder); a bare .mkv path
                                works too

Options may follow a ``?`` as ``key=value`` pairs (``images:tum/depth?scale=5000``) or be
passed as keyword arguments to :func:`open_depth`; keyword arguments win.
"""

from __future__ import annotations

import abc
import dataclasses
import importlib
import math
import urllib.parse
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from hw.errors import BackendUnavailable, FrameError, UriError

#: Image file endings the images backend reads.
IMAGE_SUFFIXES = (".png", ".tif", ".tiff")


@dataclasses.dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics of a depth image.

    ``width``/``height`` in pixels; focal lengths ``fx``/``fy`` and principal point
    ``cx``/``cy`` in pixels (pixel centres at integer coordinates, so a centred VGA principal
    point is 319.5, 239.5).  Raises :class:`FrameError` for values that make no sense.
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    def __post_init__(self) -> None:
        for name in ("width", "height"):
            value = getattr(self, name)
            if not isinstance(value, (int, np.integer)) or not 0 < value <= 100_000:
                raise FrameError(
                    f"intrinsics {name}={value!r}: must be a whole number of pixels in 1..100000"
                )
        for name in ("fx", "fy", "cx", "cy"):  # a number, kept as a float (not "525")
            value = getattr(self, name)
            if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float,
                                                                              np.number)):
                raise FrameError(f"intrinsics {name}={value!r}: must be a number of pixels")
            object.__setattr__(self, name, float(value))
        for name in ("fx", "fy"):
            value = getattr(self, name)
            if not math.isfinite(value) or value <= 0:
                raise FrameError(
                    f"intrinsics {name}={value!r}: the focal length must be a finite number of "
                    "pixels > 0 (OpenNI's VGA default is 525)"
                )
        for name, size in (("cx", self.width), ("cy", self.height)):
            value = getattr(self, name)
            if not math.isfinite(value) or not -size <= value <= 2 * size:
                raise FrameError(
                    f"intrinsics {name}={value!r}: the principal point must be finite and near "
                    f"the image (0..{size} pixels); for a {self.width}x{self.height} image the "
                    f"centre is {(size - 1) / 2}"
                )

    @classmethod
    def openni_default(cls, width: int = 640, height: int = 480) -> Intrinsics:
        """OpenNI's nominal VGA intrinsics (fx = fy = 525, centre 319.5, 239.5), scaled to the
        given resolution (e.g. 320x240 QVGA)."""
        return cls(640, 480, 525.0, 525.0, 319.5, 239.5).scaled(width, height)

    def scaled(self, width: int, height: int) -> Intrinsics:
        """The same camera at another resolution (same field of view)."""
        sx, sy = width / self.width, height / self.height
        return Intrinsics(
            int(width),
            int(height),
            self.fx * sx,
            self.fy * sy,
            (self.cx + 0.5) * sx - 0.5,
            (self.cy + 0.5) * sy - 0.5,
        )

    @classmethod
    def parse(cls, text: str, width: int = 640, height: int = 480) -> Intrinsics:
        """``"fx,fy,cx,cy"`` (pixels) for an image of ``width`` x ``height``."""
        try:
            fx, fy, cx, cy = (float(part) for part in text.split(","))
        except ValueError:
            raise FrameError(
                f"intrinsics {text!r}: expected four numbers 'fx,fy,cx,cy', e.g. "
                "'525,525,319.5,239.5'"
            ) from None
        return cls(width, height, fx, fy, cx, cy)

    def as_array(self) -> np.ndarray:
        """``[fx, fy, cx, cy]`` as float64, for the numeric kernels."""
        return np.array([self.fx, self.fy, self.cx, self.cy], dtype=np.float64)


@dataclasses.dataclass(frozen=True, eq=False)
class DepthFrame:
    """One depth image.

    ``depth``: (H, W) uint16, millimetres, 0 = no reading.  ``timestamp_us``: the device's
    timestamp in microseconds (for recordings, as recorded; for image folders, from the file
    name when it is a number of seconds, else index / 30 s).  ``index``: the frame number as the
    source counts it (gaps mean dropped frames).  ``intrinsics`` match ``depth``'s shape.
    """

    depth: np.ndarray
    timestamp_us: int
    index: int
    intrinsics: Intrinsics

    def __post_init__(self) -> None:
        depth = self.depth
        if not isinstance(depth, np.ndarray) or depth.dtype != np.uint16 or depth.ndim != 2:
            described = (
                f"{depth.dtype} array of shape {depth.shape}"
                if isinstance(depth, np.ndarray)
                else type(depth).__name__
            )
            raise FrameError(
                f"depth must be a 2-D uint16 array in millimetres, got a {described}"
            )
        height, width = depth.shape
        if (width, height) != (self.intrinsics.width, self.intrinsics.height):
            raise FrameError(
                f"depth is {width}x{height} but the intrinsics are for "
                f"{self.intrinsics.width}x{self.intrinsics.height}; pass intrinsics for this "
                "resolution (Intrinsics.scaled)"
            )

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W) in pixels."""
        return self.depth.shape  # type: ignore[return-value]

    def valid_fraction(self) -> float:
        """Fraction of pixels with a reading (depth > 0)."""
        return float(np.count_nonzero(self.depth)) / self.depth.size


@dataclasses.dataclass
class SourceStats:
    """What a source has delivered so far: frames handed out, frames it knows were lost
    (gaps in the device's frame numbers), and restarts of its reader."""

    delivered: int = 0
    dropped: int = 0
    restarts: int = 0


class DepthSource(abc.ABC):
    """A stream of :class:`DepthFrame` objects: a camera or a recording.

    Use it as a context manager and iterate, or call :meth:`read` with a timeout::

        with open_depth("images:sim_fixtures/frames/") as source:
            for frame in source:
                ...

    ``read`` returns ``None`` once a finite recording has ended; a live camera never ends but
    raises :class:`hw.errors.FrameTimeout` when no frame came in time and
    :class:`hw.errors.DeviceLost` when it is gone.
    """

    #: The URI this source was opened from.
    uri: str = ""

    def __init__(self) -> None:
        self.stats = SourceStats()

    @property
    @abc.abstractmethod
    def intrinsics(self) -> Intrinsics:
        """The intrinsics of the frames this source delivers."""

    @abc.abstractmethod
    def open(self) -> None:
        """Start the stream.  Calling it on an open source does nothing."""

    @abc.abstractmethod
    def close(self) -> None:
        """Stop the stream and release the device.  Safe to call more than once."""

    @abc.abstractmethod
    def read(self, timeout: float | None = 1.0) -> DepthFrame | None:
        """The next frame, waiting at most ``timeout`` seconds (``None``: as long as it takes);
        ``None`` at the end of a recording."""

    def __enter__(self) -> DepthSource:
        self.open()
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def __iter__(self) -> Iterator[DepthFrame]:
        """Every frame until the recording ends (a live camera never ends).  Waits as long as a
        frame takes; a lost device still raises.  Use :meth:`read` for a bounded wait."""
        while True:
            frame = self.read(timeout=None)
            if frame is None:
                return
            yield frame


# scheme -> "module:factory"; the factory takes (target: str, **options) -> DepthSource
_BACKENDS: dict[str, str] = {
    "images": "hw.images:open_images",
    "pcd": "hw.pcd:open_pcd",
    "mkv": "hw.azure_kinect:open_mkv",
    "rosbag": "hw.rosbag:open_rosbag",
    "oni": "hw.openni2:open_recording",
    "openni2": "hw.openni2:open_device",
    "realsense": "hw.realsense:open_realsense",
}

# what to install when a backend's import fails
_INSTALL_HINTS: dict[str, str] = {
    "images": "numpy (pip install numpy)",
    "pcd": "pypcd4 (pip install pypcd4)",
    "mkv": "numpy (pip install numpy)",
    "rosbag": "rosbags (pip install rosbags)",
    "oni": "Debian's libopenni2-0 (apt-get install libopenni2-0) and the 'openni' binding "
    "(pip install openni)",
    "openni2": "Debian's libopenni2-0 (apt-get install libopenni2-0) and the 'openni' binding "
    "(pip install openni)",
    "realsense": "librealsense's Python binding (pip install pyrealsense2, the realsense extra; "
    "on ARM boards build librealsense with its Python binding)",
}


def parse_uri(uri: str) -> tuple[str, str, dict[str, str]]:
    """Split a depth URI into ``(scheme, target, options)``.

    A bare path is given the scheme its ending implies (``.oni`` -> ``oni``; ``.bag``,
    ``.db3``, ``.mcap`` or a folder holding ``metadata.yaml`` -> ``rosbag``; ``.pcd`` ->
    ``pcd``; ``.mkv`` -> ``mkv``; an image or another folder -> ``images``).  Raises
    :class:`UriError` for an unknown scheme or an empty target.
    """
    if not isinstance(uri, str) or not uri.strip():
        raise UriError(f"depth URI {uri!r}: expected e.g. 'openni2://', 'oni:file.oni' or "
                       "'images:folder/'")
    text = uri.strip()
    target, _, query = text.partition("?")
    options = dict(urllib.parse.parse_qsl(query, keep_blank_values=True)) if query else {}
    if "://" in target:
        scheme, _, rest = target.partition("://")
    elif ":" in target and not Path(target).exists() and len(target.split(":", 1)[0]) > 1:
        scheme, _, rest = target.partition(":")
    else:
        scheme, rest = _scheme_of_path(target), target
    scheme = scheme.lower()
    if scheme not in _BACKENDS:
        raise UriError(
            f"depth URI {uri!r}: unknown scheme {scheme!r}; known schemes are "
            + ", ".join(f"'{name}:'" for name in sorted(_BACKENDS))
            + " (a bare path ending in .oni, .bag, .db3, .mcap, .pcd, .mkv, .png or .tif, or a "
            "folder, works too)"
        )
    if scheme not in ("openni2", "realsense") and not rest:
        raise UriError(f"depth URI {uri!r}: the {scheme!r} scheme needs a path after ':'")
    return scheme, rest, options


#: Bare-path endings and the scheme they imply (images and folders aside).
_SUFFIX_SCHEMES = {".oni": "oni", ".bag": "rosbag", ".db3": "rosbag", ".mcap": "rosbag",
                   ".pcd": "pcd", ".mkv": "mkv"}


def _scheme_of_path(path: str) -> str:
    suffix = Path(path).suffix.lower()
    if suffix in _SUFFIX_SCHEMES:
        return _SUFFIX_SCHEMES[suffix]
    if Path(path).is_dir():
        return "rosbag" if (Path(path) / "metadata.yaml").is_file() else "images"
    if suffix in IMAGE_SUFFIXES or not Path(path).exists():
        return "images"  # (a missing path: let the backend say so)
    if suffix in (".ply", ".npz", ".npy", ".xyz"):
        raise UriError(f"{path}: a {suffix} file is not a depth source; depth sources are 16-bit "
                       "depth images (PNG, TIFF), folders of them, .oni recordings, ROS bags, "
                       "organized .pcd clouds, Azure Kinect .mkv recordings and openni2:// "
                       "cameras")
    raise UriError(
        f"depth URI {path!r}: cannot tell the backend from the file name; use 'oni:{path}', "
        f"'rosbag:{path}', 'pcd:{path}', 'mkv:{path}' or 'images:{path}'"
    )


def open_depth(uri: str, **options: Any) -> DepthSource:
    """Open the depth source a URI names (see the module docstring).  The source is returned
    unopened: use it in a ``with`` block.

    Raises :class:`UriError` for an unknown scheme and :class:`BackendUnavailable`, naming what
    to install, when the backend's library is missing.
    """
    scheme, target, uri_options = parse_uri(uri)
    module_name, _, factory_name = _BACKENDS[scheme].partition(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise BackendUnavailable(
            f"depth URI {uri!r} needs {_INSTALL_HINTS[scheme]}; importing {module_name} "
            f"failed: {exc}"
        ) from exc
    factory = getattr(module, factory_name)
    source: DepthSource = factory(target, **{**uri_options, **options})
    source.uri = uri
    return source
