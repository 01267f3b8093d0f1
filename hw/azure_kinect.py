"""Azure Kinect recordings as a depth source: ``mkv:recording.mkv`` (a bare ``.mkv`` path works
too), as ``k4arecorder`` writes them (and Orbbec's Femto cameras through their K4A wrapper).

The DEPTH track's frames (millimetres, 0 = no reading; 640 x 576 in the NFOV unbinned mode) are
delivered with their time in the recording.  Intrinsics: ``?intrinsics=fx,fy,cx,cy`` (the
frames then taken as they are), else the factory calibration the recorder attaches
(``calibration.json``) for the depth mode the file names (``K4A_DEPTH_MODE``, else the one of
the frames' size), converted as the SDK converts it, and the frames undistorted by its lens
model into that pinhole camera (the rest of the project reads pinhole depth: the NFOV lens
moves a reading up to ~80 px from where a pinhole puts it).  ``rate=`` paces delivery,
``loop=1`` starts again after the last frame (timestamps keep increasing).  The source's
``info`` names the camera ("Azure Kinect", the ``auto`` noise profile's key), its serial number
and depth mode.  Read with :mod:`hw.mkv_format`, frame by frame from the file.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from hw.depth import DepthFrame, DepthSource, Intrinsics
from hw.errors import DepthFileError, DeviceError, FrameError, UriError
from hw.mkv_format import DepthBlock, MkvFile, MkvTrack
from hw.options import LapClock, Pacer, flag, intrinsics_option, positive

__all__ = ["DEPTH_MODES", "AzureRecordingSource", "DepthCalibration", "depth_calibration",
           "open_mkv", "undistort", "undistortion_table"]

_OPTIONS = ("intrinsics", "rate", "loop")

#: The depth modes of the Azure Kinect SDK's mode conversion
#: (transformation_get_mode_specific_depth_camera_calibration): the normalised calibration
#: scaled to the binned sensor, then cropped by ``crop`` px to ``size``.
DEPTH_MODES = {
    "NFOV_2X2BINNED": {"binned": (512, 512), "crop": (96, 90), "size": (320, 288)},
    "NFOV_UNBINNED": {"binned": (1024, 1024), "crop": (192, 180), "size": (640, 576)},
    "WFOV_2X2BINNED": {"binned": (512, 512), "crop": (0, 0), "size": (512, 512)},
    "WFOV_UNBINNED": {"binned": (1024, 1024), "crop": (0, 0), "size": (1024, 1024)},
}


@dataclasses.dataclass(frozen=True)
class DepthCalibration:
    """The depth camera in one mode: its pinhole ``intrinsics``, the lens's Brown-Conrady
    ``distortion`` (k1, k2, k3, k4, k5, k6, p1, p2: a rational radial model and tangential
    terms, OpenCV's order aside) and ``metric_radius`` (beyond it, in the z = 1 plane, the
    model is not valid)."""

    intrinsics: Intrinsics
    distortion: tuple[float, ...]
    metric_radius: float


def depth_calibration(calibration: str | bytes, mode: str, where: str) -> DepthCalibration:
    """The depth camera's calibration for a depth ``mode`` (a :data:`DEPTH_MODES` key) from the
    text of an Azure Kinect ``calibration.json`` (``where`` names it in errors).

    The factory calibration (``Cameras`` -> ``CALIBRATION_CameraLocationD0``) holds
    Brown-Conrady parameters cx, cy, fx, fy, k1-k6, codx, cody, p2, p1 (the centre of
    distortion only for another model), the first four normalised to the 1024 x 1024 sensor
    with (0, 0) the top-left corner of the top-left pixel.  As the SDK converts them to a
    mode: scale by the mode's binned sensor size, subtract the mode's crop offset, and
    subtract half a pixel (pixel centres at integer coordinates, as :class:`Intrinsics` counts
    them).  Raises :class:`DepthFileError` for another file and :class:`UriError` for an
    unknown mode."""
    if mode not in DEPTH_MODES:
        raise UriError(f"{where}: unknown depth mode {mode!r}; known: {', '.join(DEPTH_MODES)}")
    try:
        cameras = json.loads(calibration)["CalibrationInformation"]["Cameras"]
        depth = [c for c in cameras if c.get("Location") == "CALIBRATION_CameraLocationD0"]
        if not depth:
            raise KeyError("no CALIBRATION_CameraLocationD0 camera")
        cam = depth[0]
        model = cam["Intrinsics"]["ModelType"]
        values = [float(v) for v in cam["Intrinsics"]["ModelParameters"][:14]]
        cx, cy, fx, fy, k1, k2, k3, k4, k5, k6, _codx, _cody, p2, p1 = values
        sensor = (int(cam["SensorWidth"]), int(cam["SensorHeight"]))
        radius = float(cam.get("MetricRadius", 0.0))
    except (ValueError, KeyError, TypeError, IndexError, AttributeError) as exc:
        raise DepthFileError(f"{where}: not an Azure Kinect calibration: {exc}") from None
    if model != "CALIBRATION_LensDistortionModelBrownConrady" or sensor != (1024, 1024):
        raise DepthFileError(f"{where}: depth camera model {model!r} on a {sensor[0]} x "
                             f"{sensor[1]} sensor; expected Brown-Conrady on the 1024 x 1024 "
                             "sensor")
    if not all(math.isfinite(v) for v in values) or not math.isfinite(radius):
        raise DepthFileError(f"{where}: the depth camera's calibration holds a value that is "
                             "not a number")
    m = DEPTH_MODES[mode]
    (bw, bh), (ox, oy), (w, h) = m["binned"], m["crop"], m["size"]
    try:
        intrinsics = Intrinsics(w, h, fx * bw, fy * bh, cx * bw - ox - 0.5, cy * bh - oy - 0.5)
    except FrameError as exc:
        raise DepthFileError(f"{where}: the depth camera's calibration makes no sense: {exc}") \
            from None
    return DepthCalibration(intrinsics, (k1, k2, k3, k4, k5, k6, p1, p2),
                            radius if radius > 0 else math.inf)


def undistortion_table(calibration: DepthCalibration) -> np.ndarray:
    """(H * W,) int64: for each pixel of the pinhole image (``calibration.intrinsics``), the
    flat index of the recorded pixel its ray falls on (nearest), or H * W where it falls
    outside the recorded image or beyond the metric radius.  ``undistort`` with it."""
    K = calibration.intrinsics
    k1, k2, k3, k4, k5, k6, p1, p2 = calibration.distortion
    v, u = np.mgrid[0:K.height, 0:K.width].astype(np.float64)
    x, y = (u - K.cx) / K.fx, (v - K.cy) / K.fy
    r2 = x * x + y * y
    radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    ud = np.rint(xd * K.fx + K.cx)
    vd = np.rint(yd * K.fy + K.cy)
    inside = (ud >= 0) & (ud < K.width) & (vd >= 0) & (vd < K.height) & \
        (r2 < calibration.metric_radius ** 2)
    table = np.full(K.width * K.height, K.width * K.height, np.int64)
    table[inside.ravel()] = (vd * K.width + ud)[inside].astype(np.int64)
    return table


def undistort(recorded: np.ndarray, table: np.ndarray) -> np.ndarray:
    """(H, W) uint16: a recorded depth image seen through a pinhole (nearest reading, so no
    depth is mixed across an edge; 0 where no recorded pixel falls), by
    :func:`undistortion_table`.  An Azure Kinect's depth is z along the optical axis, which
    moving a reading to another pixel leaves true."""
    flat = np.append(recorded.ravel(), np.uint16(0))
    return flat[table].reshape(recorded.shape)


class AzureRecordingSource(DepthSource):
    """The DEPTH frames of an Azure Kinect recording (see the module docstring).  Made by
    :func:`open_mkv`; opening reads the tracks, tags and calibration and checks the first
    frame's block, so a wrong file fails at :meth:`open` with a :class:`DepthFileError`.

    A frame that cannot be read (a block of the wrong size, a file cut short) raises
    :class:`DepthFileError` and counts as dropped; the recording's walk ends there (the next
    read starts the next lap when looping, else returns None)."""

    def __init__(self, path: Path, *, intrinsics: Intrinsics | str | None,
                 rate: float | None, loop: bool) -> None:
        super().__init__()
        self.path = path
        self.rate = rate
        self.loop = loop
        self.info: dict[str, Any] = {}
        self._given_intrinsics = intrinsics
        self._intrinsics: Intrinsics | None = None
        self._pacer = Pacer(rate)
        self._file: MkvFile | None = None
        self._track: MkvTrack | None = None
        self._blocks: Iterator[DepthBlock] | None = None
        self._pending: DepthBlock | None = None
        self._undistortion: np.ndarray | None = None
        self._position = 0
        self._clock = LapClock()

    def __repr__(self) -> str:
        return f"<AzureRecordingSource {self.path}>"

    @property
    def intrinsics(self) -> Intrinsics:
        """The frames' intrinsics (opens the recording to learn them, if needed)."""
        if self._intrinsics is None:
            self.open()
        assert self._intrinsics is not None
        return self._intrinsics

    def open(self) -> None:
        """Open the recording and start at its first frame (again, after :meth:`close`)."""
        if self._file is not None:
            return
        self._file = MkvFile(self.path)
        self._position = 0
        self._clock.reset()
        try:
            tags = self._file.tags()
            self._track = self._depth_track()
            self._intrinsics, self._undistortion = self._camera(tags)
            self.info = {"name": "Azure Kinect", "serial": tags.get("K4A_DEVICE_SERIAL_NUMBER"),
                         "depth_mode": tags.get("K4A_DEPTH_MODE")}
            self._blocks = self._file.blocks(self._track)
            self._peek()
            if self._pending is None:
                raise self._file.fail("no DEPTH frame in the recording")
        except BaseException:
            self.close()
            raise
        self._pacer.reset()

    def close(self) -> None:
        """Close the file; a later :meth:`open` starts from the first frame.  Safe to repeat."""
        file, self._file = self._file, None
        self._blocks = None
        self._pending = None
        if file is not None:
            file.close()

    def read(self, timeout: float | None = 1.0) -> DepthFrame | None:
        """The next frame; ``None`` after the last one when not looping.

        With a ``rate``, waits until the frame is due; if that is more than ``timeout`` seconds
        away, waits ``timeout`` and raises :class:`FrameTimeout` (the frame stays next)."""
        if self._file is None:
            raise DeviceError(f"{self!r} is not open: call open() or use it in a 'with' block")
        if self._pending is None:
            if self._blocks is not None:
                self._peek()
            if self._pending is None and self.loop and self._clock.lap_frames:
                self._clock.next_lap()
                self._blocks = self._file.blocks(self._track)
                self._peek()
            if self._pending is None:
                return None
        self._pacer.wait(timeout, repr(self))
        block, self._pending = self._pending, None
        assert self._track is not None
        try:
            depth = self._file.frame(block, self._track)
            if self._undistortion is not None:
                depth = undistort(depth, self._undistortion)
        except DepthFileError:
            self.stats.dropped += 1
            self._blocks = None  # the walk ends at a broken block
            raise
        index = self._position
        self._position += 1
        frame = DepthFrame(depth, self._clock.stamp(block.timestamp_us), index, self.intrinsics)
        self.stats.delivered += 1
        return frame

    # the recording's contents -----------------------------------------------------------------
    def _depth_track(self) -> MkvTrack:
        assert self._file is not None
        tracks = self._file.tracks()
        chosen = [t for t in tracks if t.name == "DEPTH"]
        if not chosen:
            raise self._file.fail("no DEPTH track (tracks: "
                                  f"{', '.join(t.name or '?' for t in tracks) or 'none'})")
        track = chosen[0]
        if track.fourcc != "b16g":
            raise self._file.fail(f"the DEPTH track's codec is {track.codec!r} / "
                                  f"{track.fourcc!r}, not the 16-bit big-endian grey 'b16g'")
        if track.width <= 0 or track.height <= 0:
            raise self._file.fail("the DEPTH track has no picture size")
        return track

    def _camera(self, tags: dict[str, str]) -> tuple[Intrinsics, np.ndarray | None]:
        """(intrinsics, undistortion table): ``?intrinsics=`` and None (the frames taken as
        they are), else the attached calibration for the file's depth mode and its
        :func:`undistortion_table`."""
        assert self._file is not None and self._track is not None
        size = (self._track.width, self._track.height)
        given = self._given_intrinsics
        if given is not None:
            intrinsics = Intrinsics.parse(given, *size) if isinstance(given, str) else given
            if (intrinsics.width, intrinsics.height) != size:
                raise FrameError(f"{self.path}: the depth frames are {size[0]}x{size[1]} but "
                                 f"the intrinsics given are for {intrinsics.width}x"
                                 f"{intrinsics.height}")
            return intrinsics, None
        by_size = [name for name, m in DEPTH_MODES.items() if m["size"] == size]
        mode = tags.get("K4A_DEPTH_MODE") or (by_size[0] if by_size else "")
        if not mode or mode not in DEPTH_MODES or DEPTH_MODES[mode]["size"] != size:
            raise self._file.fail(f"depth mode {mode or '(none)'!r} with {size[0]} x {size[1]} "
                                  "frames is none of the Azure Kinect's; give the camera's "
                                  "?intrinsics=fx,fy,cx,cy")
        name = tags.get("K4A_CALIBRATION_FILE") or "calibration.json"
        calibration = self._file.attachment(name)
        if calibration is None:
            raise self._file.fail(f"no {name} attached (the factory calibration); give the "
                                  "camera's ?intrinsics=fx,fy,cx,cy")
        camera = depth_calibration(calibration, mode, f"{self.path} ({name})")
        return camera.intrinsics, undistortion_table(camera)

    def _peek(self) -> None:
        """The next DEPTH block, or None at the end of the walk (a broken one: raised once,
        counted as dropped, and the walk ends)."""
        assert self._blocks is not None
        try:
            self._pending = next(self._blocks, None)
        except DepthFileError:
            self._blocks = None
            if self._position:  # not at open: frames of this lap are lost
                self.stats.dropped += 1
            raise
        if self._pending is None:
            self._blocks = None


def open_mkv(target: str, *, intrinsics: Any = None, rate: Any = None, loop: Any = False,
             **unknown: Any) -> AzureRecordingSource:
    """The ``mkv:`` backend of :func:`hw.depth.open_depth`.

    ``target``: an Azure Kinect recording (``.mkv``).  Options (Python values, or the strings
    of a URI query): ``intrinsics`` an :class:`Intrinsics` or ``"fx,fy,cx,cy"`` instead of the
    attached calibration; ``rate`` Hz to pace delivery at; ``loop`` 1/0.  Raises
    :class:`UriError` for bad or unknown options and :class:`DepthFileError` when the target is
    missing.  The source is returned unopened."""
    if unknown:
        raise UriError(f"mkv option(s) {', '.join(sorted(unknown))} unknown; the mkv backend "
                       f"takes {', '.join(_OPTIONS)}")
    rate_value = None if rate is None or rate == "" else positive(
        "mkv", "rate", rate, "frames per second; leave it out to read as fast as possible")
    path = Path(target)
    if not path.is_file():
        raise DepthFileError(f"{target}: no such file (expected an Azure Kinect recording, "
                             ".mkv)")
    return AzureRecordingSource(path, intrinsics=intrinsics_option("mkv", intrinsics),
                                rate=rate_value, loop=flag("mkv", "loop", loop))
