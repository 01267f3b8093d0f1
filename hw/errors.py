"""Errors raised by the device layer.

One small hierarchy, so that a caller can catch ``HwError`` for "anything the hardware or a
recording did wrong" and still tell the cases apart.  Every message names the problem and what
an operator can do about it.

HwError
 +-- UriError             unknown scheme or malformed URI ("opn2://", "images:")
 +-- BackendUnavailable   the library a backend needs is not installed (names the package)
 +-- DepthFileError       a depth image or recording is missing, unreadable or corrupt,
 |                        or a folder holds no depth images
 +-- FrameError           a frame whose array or intrinsics make no sense (wrong dtype/shape)
 +-- DeviceError          a camera problem
 |    +-- DeviceNotFound  no camera plugged in, or none with that serial number
 |    +-- DeviceLost      the camera was streaming and disappeared (unplugged, USB reset)
 |    +-- FrameTimeout    no frame arrived within the read timeout
 +-- PortError            a serial port cannot be opened or vanished
 +-- ArgumentError        a value handed to a hw function it cannot use (a count < 1, a
                          timeout <= 0, an unknown kind)
"""

from __future__ import annotations


class HwError(Exception):
    """Base class of every error raised by ``hw``."""


class UriError(HwError, ValueError):
    """A source or port URI with an unknown scheme or a malformed target.

    Example: ``open_depth("kinect://0")`` -- the message lists the schemes that exist.
    """


class BackendUnavailable(HwError, ImportError):
    """A backend's library is missing.  The message names what to install.

    Example: ``open_depth("openni2://")`` on a machine without ``libopenni2-0``.
    """


class DepthFileError(HwError, OSError):
    """A depth image or recording cannot be used.

    Examples: the path does not exist; the PNG is 8-bit colour, not 16-bit depth; the file is
    truncated; a folder contains no ``.png``/``.tif`` files; an ``.oni`` file is corrupt.
    """


class NotDepthImageError(DepthFileError):
    """An image that decodes but holds no depth: colour, palette, 8-bit, floating point."""


class FrameError(HwError, ValueError):
    """A frame or intrinsics that make no sense.

    Examples: depth of dtype float64 instead of uint16; a (480, 640, 3) array; fx <= 0;
    intrinsics for 640x480 on a 320x240 image.
    """


class DeviceError(HwError):
    """A camera problem."""


class DeviceNotFound(DeviceError):
    """No camera is connected, or none matches the requested URI / serial number."""


class DeviceLost(DeviceError):
    """The camera was streaming and is gone (unplugged, USB reset, driver crashed)."""


class FrameTimeout(DeviceError, TimeoutError):
    """No frame arrived within the read timeout.  The source may still recover."""


class PortError(HwError, OSError):
    """A serial port cannot be opened, or vanished while in use (USB adapter unplugged)."""


class ArgumentError(HwError, ValueError):
    """A value handed to a hw function that it cannot use.

    Examples: ``Backoff(0, 1)``; ``record_oni(source, path, frames=0)``.
    """
