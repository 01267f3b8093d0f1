"""Depth image files: 16-bit grayscale PNG and TIFF, read and written with Pillow (a plain
16-bit grayscale PNG, the usual depth image, read by :mod:`hw.png16`).

    depth = read_image("frame.png")        # (H, W) uint16 (uint8 for an 8-bit gray file)
    write_png("out.png", depth)            # atomically

Every failure is a :class:`hw.errors.DepthFileError` naming the file: missing, a folder,
empty, truncated or corrupt, not a PNG or TIFF, or not grayscale ("RGB PNG is not a depth
image").  Only the first page of a multi-page TIFF is read.
"""

from __future__ import annotations

import io
import os
import warnings
from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

from hw.atomic import write_atomically
from hw.errors import DepthFileError, FrameError, NotDepthImageError
from hw.png16 import decode_png16

__all__ = ["decode_image", "read_file", "read_image", "write_png"]

#: Largest image accepted, pixels (a 16k x 16k depth image; a header asking for more is refused
#: before anything is decoded).
MAX_PIXELS = 16384 * 16384

# Pillow modes of grayscale images -> the dtype of their samples
_GRAY = {"I;16": np.uint16, "I;16L": np.uint16, "I;16B": np.uint16, "I;16N": np.uint16,
         "L": np.uint8, "I": None}
_WHAT = {"RGB": "RGB", "RGBA": "RGBA", "LA": "gray+alpha", "La": "gray+alpha", "P": "palette",
         "PA": "palette+alpha", "CMYK": "CMYK", "YCbCr": "YCbCr", "1": "1-bit (black and white)",
         "F": "floating-point", "I;16S": "signed 16-bit"}


def read_file(path: str | os.PathLike) -> bytes:
    """The bytes of ``path``; :class:`DepthFileError` when it is missing or unreadable."""
    try:
        return Path(path).read_bytes()
    except FileNotFoundError:
        raise DepthFileError(f"{path}: no such file") from None
    except IsADirectoryError:
        raise DepthFileError(f"{path}: is a folder, expected an image file") from None
    except OSError as exc:
        raise DepthFileError(f"{path}: cannot read it ({exc.strerror or exc})") from None


def read_image(source: str | os.PathLike | bytes) -> np.ndarray:
    """Decode a grayscale PNG or TIFF (a path, or the file's bytes): an (H, W) uint16 array
    for 16-bit samples, uint8 for 8-bit ones."""
    if isinstance(source, (bytes, bytearray, memoryview)):
        return decode_image(bytes(source), "image data")
    return decode_image(read_file(source), str(source))


def decode_image(data: bytes, name: str) -> np.ndarray:
    """The (H, W) uint16 / uint8 samples of the PNG or TIFF in ``data``; ``name`` is used in
    error messages."""
    if not data:
        raise DepthFileError(f"{name}: the file is empty")
    kind = "PNG" if data.startswith(b"\x89PNG\r\n\x1a\n") else \
        "TIFF" if data[:4] in (b"II*\x00", b"MM\x00*") else None
    if kind is None:
        what = "BigTIFF is not supported" if data[:4] in (b"II+\x00", b"MM\x00+") else \
            "neither a PNG nor a TIFF (by its first bytes)"
        raise DepthFileError(f"{name}: {what}; depth images are 16-bit grayscale PNG or TIFF")
    if kind == "PNG":  # the depth PNG's usual form, decoded without Pillow
        samples = decode_png16(data, name, MAX_PIXELS)
        if samples is not None:
            return samples
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # Pillow's notes on damaged tags: the error says it
            warnings.simplefilter("error", Image.DecompressionBombWarning)
            with Image.open(io.BytesIO(data), formats=[kind]) as image:
                width, height = image.size
                if width * height > MAX_PIXELS:
                    raise DepthFileError(f"{name}: {width}x{height} pixels is too large for a "
                                         "depth image")
                mode = image.mode
                if mode not in _GRAY:
                    raise NotDepthImageError(f"{name}: {_WHAT.get(mode, mode)} {kind} is not "
                                             "a depth image; depth images are 16-bit grayscale")
                image.load()
                samples = np.array(image)
    except DepthFileError:
        raise
    except UnidentifiedImageError:
        raise DepthFileError(f"{name}: truncated or corrupt {kind}: its header cannot be "
                             "read") from None
    except (OSError, ValueError, SyntaxError, EOFError, Image.DecompressionBombError,
            Image.DecompressionBombWarning) as exc:
        raise DepthFileError(f"{name}: truncated or corrupt {kind} ({exc})") from None
    dtype = _GRAY[mode]
    if dtype is None:  # 32-bit integer samples: depth only when they fit 16 bits
        if samples.size and (samples.min() < 0 or samples.max() > 0xFFFF):
            raise NotDepthImageError(f"{name}: 32-bit {kind} samples beyond 0..65535 are not "
                                     "a depth image")
        dtype = np.uint16
    return np.ascontiguousarray(samples.astype(dtype, copy=False))


def write_png(path: str | os.PathLike, array: np.ndarray, *, level: int = 6) -> None:
    """Write ``array`` as a PNG, atomically (temp file in the same folder, fsync, rename).

    ``array``: (H, W) uint16 (16-bit gray, e.g. depth in mm), (H, W) uint8 (8-bit gray) or
    (H, W, 3) uint8 (RGB).  ``level``: zlib level 0-9.  Raises :class:`FrameError` for another
    dtype, shape or level, :class:`DepthFileError` when the file cannot be written.
    """
    array = np.asarray(array)
    if not (array.ndim == 2 and array.dtype in (np.uint16, np.uint8)) and \
            not (array.ndim == 3 and array.shape[2] == 3 and array.dtype == np.uint8):
        raise FrameError(f"write_png: an (H, W) uint16 / uint8 or (H, W, 3) uint8 array, got "
                         f"{array.dtype} {array.shape}")
    if 0 in array.shape[:2]:
        raise FrameError(f"write_png: an image needs at least one pixel, got {array.shape}")
    if isinstance(level, bool) or not isinstance(level, int) or not 0 <= level <= 9:
        raise FrameError(f"write_png: level={level!r}: a zlib level 0..9")
    image = Image.fromarray(np.ascontiguousarray(array))
    buf = io.BytesIO()
    image.save(buf, format="PNG", compress_level=level)
    try:
        write_atomically(path, buf.getvalue())
    except OSError as exc:
        raise DepthFileError(f"{path}: cannot write it ({exc.strerror or exc})") from None
