"""Device drivers for robot_change: depth cameras, recordings, image folders, serial ports.

A leaf package: it imports nothing from ``robot_change``.  Open a depth source by URI with
:func:`hw.depth.open_depth`.
"""

from hw.depth import DepthFrame, DepthSource, Intrinsics, SourceStats, open_depth
from hw.errors import (
    BackendUnavailable,
    DepthFileError,
    DeviceError,
    DeviceLost,
    DeviceNotFound,
    FrameError,
    FrameTimeout,
    HwError,
    NotDepthImageError,
    PortError,
    UriError,
)

__all__ = [
    "BackendUnavailable",
    "DepthFileError",
    "DepthFrame",
    "DepthSource",
    "DeviceError",
    "DeviceLost",
    "DeviceNotFound",
    "FrameError",
    "FrameTimeout",
    "HwError",
    "Intrinsics",
    "NotDepthImageError",
    "PortError",
    "SourceStats",
    "UriError",
    "open_depth",
]
