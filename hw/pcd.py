"""Organized PCD clouds as a depth source: ``pcd:cloud.pcd`` or a folder of them.

An *organized* cloud (``WIDTH`` x ``HEIGHT`` = the image, one point per pixel, NaN where there is
no reading; as PCL's OpenNI grabber and ``pcl_openni_pcd_recorder`` save them) is a depth image
in disguise: the z of each point, in the camera's frame, is the pixel's depth (metres ->
millimetres, rounded; NaN, z <= 0 and beyond 65.535 m -> 0).  The camera's frame is the one the
file's ``VIEWPOINT`` gives (its pose in the points' frame; PCL's tools write it in the optical
convention, looking along +z, or in the viewer's, looking along -z with y up: the one that puts
the points in front of the camera is taken).  A cloud that is not organized (``HEIGHT 1``) is
refused: it has lost the pixel grid.

Intrinsics: ``?fx=&fy=&cx=&cy=`` (pixels; any of them), the rest fitted to the points
themselves (``u = fx x / z + cx``, least squares over every valid point; used when the fit is
exact to 0.5 px, as it is for a grabber's cloud), else OpenNI's nominal Kinect / Xtion values
for the image's size (:meth:`Intrinsics.openni_default`).  A folder is read like an image
folder (:mod:`hw.images`): natural name order, timestamps from PCL grabber names
(``frame_20121214T142255.814212.pcd``), ``rate=``, ``loop=``, ``pattern=``.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any

import numpy as np

from hw.depth import Intrinsics
from hw.errors import DepthFileError, UriError
from hw.images import ImageFolderSource, list_images
from hw.options import flag, positive
from hw.pointfile import PcdCloud, pose_of_viewpoint, read_pcd

try:  # the backend's library: hw.depth.open_depth reports it missing with what to install
    import pypcd4  # noqa: F401
except ImportError as exc:  # pragma: no cover - exercised without pypcd4 installed
    raise ImportError(f"pypcd4 is not installed ({exc})") from exc

__all__ = ["PcdSource", "cloud_to_depth", "fit_pinhole", "open_pcd"]

log = logging.getLogger(__name__)

_CAMERA = ("fx", "fy", "cx", "cy")
_OPTIONS = (*_CAMERA, "rate", "loop", "pattern")
#: A fit of the intrinsics to a cloud's points is used when its RMS residual is below this, px.
FIT_TOLERANCE_PX = 0.5


def cloud_to_depth(cloud: PcdCloud, where: str) -> tuple[np.ndarray, np.ndarray]:
    """An organized cloud -> ((H, W) uint16 depth mm, (H, W, 3) float64 points in the camera's
    frame, NaN where there is no reading).  Raises :class:`DepthFileError` for an unorganized
    cloud or one whose points do not lie in front of its camera."""
    if not cloud.organized:
        raise DepthFileError(
            f"{where}: the cloud is not organized (WIDTH {cloud.width}, HEIGHT {cloud.height}"
            "), so it has no pixel grid to make a depth image of; a depth source needs "
            "an organized cloud (WIDTH x HEIGHT = the image), as PCL's OpenNI grabber saves")
    pose = pose_of_viewpoint(cloud.viewpoint)  # camera -> the file's frame
    points = (cloud.points.astype(np.float64) - pose[:3, 3]) @ pose[:3, :3]
    valid = np.all(np.isfinite(points), axis=1)
    if np.count_nonzero(points[valid, 2] > 0) * 2 < np.count_nonzero(valid):
        flipped = points * np.array([1.0, -1.0, -1.0])  # a camera looking along -z, y up
        if np.count_nonzero(flipped[valid, 2] > 0) * 2 < np.count_nonzero(valid):
            raise DepthFileError(f"{where}: most points lie behind the camera its VIEWPOINT "
                                 f"{cloud.viewpoint} describes, whichever way it looks")
        log.info("%s: VIEWPOINT %s is a viewer's camera (looking along -z); read as such",
                 where, cloud.viewpoint)
        points = flipped
    points = points.reshape(cloud.height, cloud.width, 3)
    z_mm = np.floor(points[..., 2] * 1000.0 + 0.5)
    good = np.all(np.isfinite(points), axis=2) & (z_mm > 0) & (z_mm <= 65535)
    depth = np.where(good, np.nan_to_num(z_mm), 0).astype(np.uint16)
    points[~good] = np.nan
    return depth, points


def fit_pinhole(points: np.ndarray) -> tuple[float, float, float, float] | None:
    """``(fx, fy, cx, cy)`` pixels fitted to an organized cloud's (H, W, 3) camera-frame points
    (``u = fx x / z + cx``, ``v = fy y / z + cy`` by least squares over the valid points), or
    None when there are fewer than 100 or the fit misses by more than
    :data:`FIT_TOLERANCE_PX` (RMS): the points were not made from a pinhole image.  Rounded to
    0.001 px."""
    height, width = points.shape[:2]
    valid = np.all(np.isfinite(points), axis=2) & (points[..., 2] > 0)
    if np.count_nonzero(valid) < 100:
        return None
    rows, cols = np.nonzero(valid)
    chosen = points[valid]
    fitted = []
    for pixel, ratio in ((cols, chosen[:, 0] / chosen[:, 2]), (rows, chosen[:, 1] / chosen[:, 2])):
        design = np.stack([ratio, np.ones_like(ratio)], axis=1)
        (focal, centre), *_ = np.linalg.lstsq(design, pixel.astype(np.float64), rcond=None)
        rms = math.sqrt(float(np.mean((design @ (focal, centre) - pixel) ** 2)))
        if not (focal > 0 and rms <= FIT_TOLERANCE_PX):
            return None
        fitted.append((round(float(focal), 3), round(float(centre), 3)))
    (fx, cx), (fy, cy) = fitted
    return fx, fy, cx, cy


class PcdSource(ImageFolderSource):
    """Organized PCD files delivered as depth frames, like a folder of depth images (see the
    module docstring).  ``camera``: the intrinsics given (any of fx, fy, cx, cy)."""

    def __init__(self, files: list[Path], *, camera: dict[str, float],
                 rate: float | None = None, loop: bool = False) -> None:
        super().__init__(files, rate=rate, loop=loop)
        self._camera = dict(camera)
        self._fitted: tuple[float, float, float, float] | None = None
        self._fit_done = False

    def __repr__(self) -> str:
        where = self.files[0] if len(self.files) == 1 else self.files[0].parent
        return f"<PcdSource {where} ({len(self.files)} files)>"

    def _decode(self, path: Path) -> np.ndarray:
        depth, points = cloud_to_depth(read_pcd(path), str(path))
        if not self._fit_done:
            self._fitted = fit_pinhole(points)
            self._fit_done = True
        return depth

    def _make_intrinsics(self, width: int, height: int) -> Intrinsics:
        nominal = Intrinsics.openni_default(width, height)
        values = dict(zip(_CAMERA, self._fitted or (nominal.fx, nominal.fy, nominal.cx,
                                                    nominal.cy), strict=True))
        values.update(self._camera)
        if self._fitted is None and len(self._camera) < 4:
            log.info("%s: intrinsics not given and not fitted to the points; using OpenNI's "
                     "nominal %s (give ?fx=&fy=&cx=&cy= for a calibrated camera)", self,
                     values)
        return Intrinsics(width, height, **values)


def open_pcd(target: str, *, rate: Any = None, loop: Any = False, pattern: Any = None,
             **options: Any) -> PcdSource:
    """The ``pcd:`` backend of :func:`hw.depth.open_depth`.

    ``target``: an organized ``.pcd`` file or a folder of them.  Options (Python values, or the
    strings of a URI query): ``fx``, ``fy``, ``cx``, ``cy`` pixels; ``rate`` Hz to pace
    delivery at; ``loop`` 1/0; ``pattern`` a glob the file names must match.  Raises
    :class:`UriError` for bad or unknown options and :class:`DepthFileError` when the target
    is missing or holds no .pcd file.  The source is returned unopened.
    """
    unknown = sorted(set(options) - set(_CAMERA))
    if unknown:
        raise UriError(f"pcd option(s) {', '.join(unknown)} unknown; the pcd backend takes "
                       f"{', '.join(_OPTIONS)}")
    camera = {}
    for name, value in options.items():
        if value is None or value == "":
            continue
        try:
            number = float(value)
        except (TypeError, ValueError):
            number = math.nan
        if not math.isfinite(number) or (name in ("fx", "fy") and number <= 0):
            raise UriError(f"pcd option {name}={value!r}: expected a number of pixels"
                           + (" > 0" if name in ("fx", "fy") else ""))
        camera[name] = number
    rate_value = None if rate is None or rate == "" else positive(
        "pcd", "rate", rate, "frames per second; leave it out to read as fast as possible")
    if pattern is not None and not isinstance(pattern, str):
        raise UriError(f"pcd option pattern={pattern!r}: expected a glob such as 'frame_*.pcd'")
    path = Path(target)
    if path.is_dir():
        files = list_images(path, pattern or None, suffixes=(".pcd",))
    elif path.is_file():
        files = [path]
    else:
        raise DepthFileError(f"{target}: no such file or folder (expected an organized .pcd "
                             "file or a folder of them)")
    return PcdSource(files, camera=camera, rate=rate_value, loop=flag("pcd", "loop", loop))
