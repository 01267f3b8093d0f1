"""OpenNI2 depth backend: live Kinect / PrimeSense / Asus Xtion cameras and ``.oni`` playback.

The native library runs in a supervised reader process (:mod:`hw.supervised`): a crash, hang
or deadlock inside libOpenNI2 (it has several: closing a file device right after opening it,
seeking, unloading with a device open) costs a restart of the reader, never the service; a
camera that stops is :class:`DeviceLost` and reconnects with back-off; a recording resumes at
its next frame.

Live cameras: the first one (``openni2://``) or one chosen by URI or serial number
(``openni2://<serial-or-uri>``); ``openni2://Oz`` opens OpenNI's DummyDevice (a synthetic
320x240 stream, for tests).  The depth mode nearest to 640x480 @ 30 fps in 1 mm units is chosen
(the choice is logged when it differs).  Frames carry the device's timestamps and frame
numbers; gaps in the numbers are counted in ``stats.dropped``.

Recordings (``oni:file.oni``) play frame by frame in lockstep (playback speed -1, repeat off):
no frame is dropped however slow the consumer, and :meth:`OpenNI2Source.read` returns ``None``
after the last one.  ``oni:file.oni?loop=1&rate=auto`` plays one like a camera instead: again
from the start after the last frame (indices and timestamps keep increasing) and paced at the
recording's fps (``rate=30`` for a given rate).  The file is checked with
:func:`hw.oni.read_oni_header` first, so a missing or corrupt file raises
:class:`DepthFileError` before the native player sees it.

Debian's ``libopenni2-0`` ships drivers for PrimeSense / Asus Xtion (PS1080) cameras.  A
Kinect v1 needs libfreenect's OpenNI2 driver (``libFreenectDriver.so``), built from source and
copied into the OpenNI2 ``Drivers`` folder.
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
import os
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import openni.openni2  # noqa: F401  -- the binding (pure Python; the native library loads in the reader)

from hw.depth import Intrinsics
from hw.errors import BackendUnavailable
from hw.oni import intrinsics_from_fov, read_oni_header
from hw.supervised import (
    ChildFailure,
    FrameFeed,
    SupervisedSource,
    ask_reader,
    reader_main,
    source_options,
)

log = logging.getLogger(__name__)

#: Environment variable naming a folder that holds ``libOpenNI2.so`` and ``OpenNI2/Drivers``.
LIBRARY_ENV = "ROBOT_CHANGE_OPENNI2_DIR"
_SYSTEM_LIBRARY_DIRS = ("/usr/lib/x86_64-linux-gnu", "/usr/lib/aarch64-linux-gnu",
                        "/usr/lib/arm-linux-gnueabihf", "/usr/lib", "/usr/local/lib")
_NO_CAMERA_HINT = (
    "Check the USB cable and power (a Kinect needs its own power supply) and that the user may "
    "access the device (udev rules). PrimeSense and Asus Xtion cameras work with Debian's "
    "libopenni2-0 as is; a Kinect v1 needs libfreenect's OpenNI2 driver (libFreenectDriver.so), "
    "built from source and copied into the OpenNI2 Drivers folder."
)
_WANTED_MODE = (640, 480, 30)
_PIXEL_FORMAT_1_MM = 100  # ONI_PIXEL_FORMAT_DEPTH_1_MM
_PIXEL_FORMAT_100_UM = 101  # ONI_PIXEL_FORMAT_DEPTH_100_UM


# =================================================================================================
# finding the native library
# =================================================================================================
def library_dir() -> str:
    """A folder that ``openni2.initialize`` accepts: ``libOpenNI2.so`` next to ``OpenNI2/Drivers``.

    Uses ``$ROBOT_CHANGE_OPENNI2_DIR`` when set; otherwise the system library (Debian's
    ``libopenni2-0`` installs only the versioned ``libOpenNI2.so.0``), exposed through a private
    folder of two symlinks in ``$XDG_CACHE_HOME/robot-change/openni2`` (``~/.cache`` by default;
    a per-user folder in the temp directory when that cannot be written).  Raises
    :class:`BackendUnavailable` naming the package to install when the library is missing.
    """
    explicit = os.environ.get(LIBRARY_ENV)
    if explicit:
        if not (Path(explicit) / "libOpenNI2.so").is_file():
            raise BackendUnavailable(
                f"${LIBRARY_ENV}={explicit} holds no libOpenNI2.so; point it at a folder with "
                "libOpenNI2.so and OpenNI2/Drivers, or unset it to use libopenni2-0"
            )
        return explicit
    for folder in _SYSTEM_LIBRARY_DIRS:
        base = Path(folder)
        drivers = base / "OpenNI2" / "Drivers"
        for name in ("libOpenNI2.so", "libOpenNI2.so.0"):
            lib = base / name
            if lib.is_file() and drivers.is_dir():
                if name == "libOpenNI2.so":
                    return str(base)
                return _symlink_folder(lib, base / "OpenNI2")
    raise BackendUnavailable(
        "the OpenNI2 library is not installed: apt-get install libopenni2-0 (or set "
        f"${LIBRARY_ENV} to a folder holding libOpenNI2.so and OpenNI2/Drivers)"
    )


def _symlink_folder(lib: Path, drivers_parent: Path) -> str:
    """Private folder (see :func:`library_dir`) with ``libOpenNI2.so`` and ``OpenNI2`` symlinks;
    (re)made atomically, so concurrent processes agree."""
    cache = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    folder = Path(cache) / "robot-change" / "openni2"
    try:
        folder.mkdir(mode=0o700, parents=True, exist_ok=True)
    except OSError:  # no writable home (a system service): a per-user folder in /tmp
        folder = Path(tempfile.gettempdir()) / f"robot-change-openni2-{os.getuid()}"
        folder.mkdir(mode=0o700, exist_ok=True)
    status = os.lstat(folder)
    if (status.st_uid != os.getuid() or status.st_mode & 0o022 or not folder.is_dir()
            or folder.is_symlink()):
        # someone else's: don't trust it
        folder = Path(tempfile.mkdtemp(prefix="robot-change-openni2-"))
    for name, target in (("libOpenNI2.so", lib), ("OpenNI2", drivers_parent)):
        link = folder / name
        if link.is_symlink() and os.readlink(link) == str(target):
            continue
        tmp = folder / f".{name}.{os.getpid()}"
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        os.symlink(target, tmp)
        os.replace(tmp, link)
    return str(folder)


# =================================================================================================
# the reader process (everything native happens here)
# =================================================================================================
def reader_entry(conn: Any, spec: dict[str, Any]) -> None:
    """What the reader process runs (:func:`hw.supervised.reader_main` with OpenNI2)."""
    reader_main(conn, spec, _OpenNI2Feed, _child_list_devices)


def _initialised(spec: dict[str, Any]) -> tuple[Any, Any]:
    try:
        from openni import _openni2 as c_api
        from openni import openni2
        openni2.initialize(spec["lib_dir"])
    except Exception as exc:  # noqa: BLE001 -- anything here means the library is unusable
        raise ChildFailure("backend", f"libOpenNI2 could not be initialised from "
                                      f"{spec['lib_dir']}: {exc}") from None
    return openni2, c_api


class _OpenNI2Feed(FrameFeed):
    """An OpenNI2 device or ``.oni`` file, in the reader process."""

    def __init__(self, spec: dict[str, Any]) -> None:
        self.spec = spec
        self.ni, self.c_api = _initialised(spec)
        self.is_file = spec["kind"] == "file"
        self.device: Any = None
        self.stream: Any = None
        self.stopped_stream = False

    def open(self) -> dict[str, Any]:
        info = self._open_file() if self.is_file else self._open_device()
        self.width, self.height = info["width"], info["height"]
        self.scale_100um = info["pixel_format"] == _PIXEL_FORMAT_100_UM
        self.buffer = np.empty((self.height, self.width), dtype=np.uint16)
        return info

    def start(self) -> None:
        self.stream.start()

    def _open_file(self) -> dict[str, Any]:
        path = self.spec["target"]
        try:
            self.device = self.ni.Device(os.fsencode(path))
            self.device.playback.set_speed(-1.0)  # manual: one frame per read, none dropped
            # looping: the player starts again after the last frame (indices keep counting)
            self.device.playback.set_repeat_enabled(bool(self.spec.get("loop")))
            self.stream = self.device.create_depth_stream()
        except Exception as exc:  # noqa: BLE001
            _fail("file", f"OpenNI2 cannot play {path}: {exc}")
        if self.stream is None:
            _fail("file", f"recording {path} holds no depth stream")
        mode = self.stream.get_video_mode()
        if mode.pixelFormat not in (_PIXEL_FORMAT_1_MM, _PIXEL_FORMAT_100_UM):
            _fail("file", f"recording {path} holds depth in pixel format {mode.pixelFormat}, "
                               "not millimetres (DEPTH_1_MM)")
        return {
            "width": mode.resolutionX, "height": mode.resolutionY, "fps": mode.fps,
            "pixel_format": int(mode.pixelFormat),
            "frames": int(self.stream.get_number_of_frames()),
            **self._fov(), "uri": path, "vendor": "", "serial": None,
            # OpenNI2's player names no camera and gives only the field of view: what
            # robot_change wrote beside them, read from the header by the parent
            "name": self.spec.get("camera", ""), "intrinsics": self.spec.get("stored"),
            "mode_note": "",
        }

    def _fov(self) -> dict[str, float | None]:
        try:
            return {"hfov": float(self.stream.get_horizontal_fov()),
                    "vfov": float(self.stream.get_vertical_fov())}
        except Exception:  # noqa: BLE001 -- drivers without a field of view (DummyDevice)
            return {"hfov": None, "vfov": None}

    def _open_device(self) -> dict[str, Any]:
        target = self.spec["target"]
        uris = [u.decode(errors="replace") for u in self.ni.Device.enumerate_uris()]
        device = None
        if not target:
            if not uris:
                _fail("not_found", "no OpenNI2 depth camera is connected. " + _NO_CAMERA_HINT)
            target = uris[0]
        open_error = ""
        try:  # a URI, listed or not (DummyDevice: "Oz")
            device = self.ni.Device(target.encode())
        except Exception as exc:  # noqa: BLE001 -- maybe a serial number
            if target in uris:
                open_error = f"; opening {target} failed: {exc}"
        if device is None:  # look for a serial number
            for uri in uris:
                with contextlib.suppress(Exception):
                    candidate = self.ni.Device(uri.encode())
                    if _serial_of(candidate, self.c_api) == target:
                        device = candidate
                        break
                    candidate.close()
        if device is None:
            present = ", ".join(uris) if uris else "none"
            _fail("not_found", f"no OpenNI2 camera with URI or serial number {target!r} "
                                    f"(connected: {present}{open_error}). " + _NO_CAMERA_HINT)
        self.device = device
        info = device.get_device_info()
        sensor = device.get_sensor_info(self.ni.SENSOR_DEPTH)
        if sensor is None:
            _fail("not_found", f"camera {target!r} has no depth sensor")
        depth_formats = (_PIXEL_FORMAT_1_MM, _PIXEL_FORMAT_100_UM)
        modes = [m for m in sensor.videoModes if int(m.pixelFormat) in depth_formats]
        if not modes:
            _fail("not_found", f"camera {target!r} offers no depth mode in millimetres")
        want_w, want_h, want_fps = _WANTED_MODE
        mode = min(modes, key=lambda m: (int(m.pixelFormat) != _PIXEL_FORMAT_1_MM,
                                         abs(m.resolutionX * m.resolutionY - want_w * want_h),
                                         abs(m.fps - want_fps)))
        self.stream = device.create_depth_stream()
        with contextlib.suppress(Exception):
            self.stream.set_video_mode(mode)
        with contextlib.suppress(Exception):
            self.stream.set_mirroring_enabled(False)
        mode = self.stream.get_video_mode()
        note = ""
        got = (mode.resolutionX, mode.resolutionY, mode.fps)
        if got != _WANTED_MODE or int(mode.pixelFormat) != _PIXEL_FORMAT_1_MM:
            unit = ("1 mm" if int(mode.pixelFormat) == _PIXEL_FORMAT_1_MM
                    else "100 um (converted to mm)")
            note = (f"camera {target!r} does not offer 640x480 @ 30 fps in 1 mm; using the nearest "
                    f"mode {mode.resolutionX}x{mode.resolutionY} @ {mode.fps} fps, {unit}")
        return {
            "width": mode.resolutionX, "height": mode.resolutionY, "fps": mode.fps,
            "pixel_format": int(mode.pixelFormat), **self._fov(),
            "uri": info.uri.decode(errors="replace"),
            "vendor": info.vendor.decode(errors="replace"),
            "name": info.name.decode(errors="replace"), "serial": _serial_of(device, self.c_api),
            "mode_note": note,
        }

    # --- streaming ------------------------------------------------------------------------
    def next_frame(self, timeout: float) -> tuple[np.ndarray, int, int] | None:
        try:
            ready = self.ni.wait_for_any_stream([self.stream], timeout)
        except Exception:  # noqa: BLE001 -- a stopped or vanished stream
            time.sleep(timeout)
            return None
        if ready is None:
            return None
        frame = self.stream.read_frame()
        try:
            raw = frame._frame
            if raw.width != self.width or raw.height != self.height or \
                    raw.dataSize < self.width * self.height * 2:
                raise ChildFailure("file" if self.is_file else "internal",
                                   f"frame {raw.frameIndex} is {raw.width}x{raw.height} "
                                   f"in {raw.dataSize} bytes, expected {self.width}x{self.height}"
                                   f" in {self.width * self.height * 2}")
            row = raw.stride // 2 if raw.stride else self.width
            src = np.ctypeslib.as_array(ctypes.cast(raw.data, ctypes.POINTER(ctypes.c_uint16)),
                                        shape=(self.height * row,))
            image = src.reshape(self.height, row)[:, :self.width]
            if self.scale_100um:
                np.floor_divide(image, 10, out=self.buffer)
            else:
                self.buffer[...] = image
            return self.buffer, int(raw.frameIndex), int(raw.timestamp)
        finally:
            frame.close()

    def simulate_loss(self) -> None:
        self.stream.stop()
        self.stopped_stream = True

    def shutdown(self) -> None:
        # Live cameras are stopped properly; a file device is left to the OS (closing one can
        # crash libOpenNI2, and there is nothing to release).
        if not self.is_file:
            with contextlib.suppress(Exception):
                if not self.stopped_stream:
                    self.stream.stop()
                self.stream.close()
                self.device.close()


def _fail(kind: str, text: str) -> None:
    raise ChildFailure(kind, text)


def _child_list_devices(spec: dict[str, Any]) -> list[dict[str, Any]]:
    openni2, c_api = _initialised(spec)
    pdevs = ctypes.POINTER(c_api.OniDeviceInfo)()
    count = ctypes.c_int()
    c_api.oniGetDeviceList(ctypes.byref(pdevs), ctypes.byref(count))
    found = []
    for i in range(count.value):
        info = pdevs[i]
        found.append({
            "uri": info.uri.decode(errors="replace"),
            "vendor": info.vendor.decode(errors="replace"),
            "name": info.name.decode(errors="replace"),
            "usb_vendor_id": int(info.usbVendorId),
            "usb_product_id": int(info.usbProductId),
        })
    c_api.oniReleaseDeviceList(pdevs)
    for entry in found:
        with contextlib.suppress(Exception):
            device = openni2.Device(entry["uri"].encode())
            serial = _serial_of(device, c_api)
            if serial:
                entry["serial"] = serial
            device.close()
    return found


def _serial_of(device: Any, c_api: Any) -> str | None:
    try:
        raw = device.get_property(c_api.ONI_DEVICE_PROPERTY_SERIAL_NUMBER, ctypes.c_char * 64)
    except Exception:  # noqa: BLE001 -- drivers without serial numbers (DummyDevice, files)
        return None
    value = raw.value.decode(errors="replace").strip() if hasattr(raw, "value") else ""
    return value or None


# =================================================================================================
# the parent side
# =================================================================================================
class OpenNI2Source(SupervisedSource):
    """A depth source read through OpenNI2 in a reader process (:mod:`hw.supervised`: options,
    failures).  Use :func:`open_device` or :func:`open_recording` (or
    :func:`hw.depth.open_depth`) to make one."""

    library = "OpenNI2"
    reader_module = __name__

    def __init__(self, kind: str, target: str, **options: Any) -> None:
        uri = f"oni:{target}" if kind == "file" else f"openni2://{target}"
        super().__init__(kind, target, uri, **options)

    def open(self) -> None:
        if not self._open:
            self._lib_dir = library_dir()
        super().open()

    def _check_file(self) -> float:
        self._header = read_oni_header(self.target)
        self._intrinsics = self._header.intrinsics()
        return float(self._header.fps)

    def _reader_spec(self) -> dict[str, Any]:
        if self.kind != "file":
            return {"lib_dir": self._lib_dir, "frames": 0}
        return {"lib_dir": self._lib_dir, "frames": self._header.frames,
                "camera": self._header.camera, "stored": self._header.stored}

    def _intrinsics_from(self, info: dict[str, Any]) -> Intrinsics:
        """Those a recording of robot_change keeps, else from the stream's field of view
        (OpenNI's VGA defaults when the driver reports none)."""
        if info.get("intrinsics") is not None:
            return Intrinsics(int(info["width"]), int(info["height"]), *info["intrinsics"])
        return intrinsics_from_fov(int(info["width"]), int(info["height"]), info.get("hfov"),
                                   info.get("vfov"))

    def _backend_hint(self) -> str:
        return "reinstall libopenni2-0 and the 'openni' binding"


# =================================================================================================
# factories, device list, recording
# =================================================================================================
def open_device(target: str = "", **options: Any) -> OpenNI2Source:
    """A live camera: ``""`` for the first one, else a URI or serial number (``"Oz"`` is the
    DummyDevice).  Returned unopened."""
    return OpenNI2Source("device", target.strip().strip("/"), **source_options("OpenNI2", options))


def open_recording(target: str, **options: Any) -> OpenNI2Source:
    """An ``.oni`` recording, played frame by frame.  Raises :class:`DepthFileError` at once for
    a missing or corrupt file.  Returned unopened."""
    return OpenNI2Source("file", str(Path(target).expanduser()),
                         **source_options("OpenNI2", options))


def list_devices(timeout: float = 10.0) -> list[dict[str, Any]]:
    """The connected OpenNI2 cameras: dicts with ``uri``, ``vendor``, ``name``, ``usb_vendor_id``,
    ``usb_product_id`` and ``serial`` when the driver reports one.  Empty when none is plugged
    in.  Enumerated in a child process, like everything native."""
    spec = {"module": __name__, "library": "OpenNI2", "kind": "list", "lib_dir": library_dir()}
    return list(ask_reader(spec, timeout, "listing OpenNI2 cameras"))


__all__ = ["OpenNI2Source", "library_dir", "list_devices", "open_device", "open_recording"]
