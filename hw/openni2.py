"""OpenNI2 depth backend: live Kinect / PrimeSense / Asus Xtion cameras and ``.oni`` playback.

The native library runs in a **child process** that hands frames to this process through a
shared-memory ring of a few frame slots and a control socket.  The child is a fresh interpreter
started with :mod:`subprocess` (not multiprocessing, whose "spawn" re-imports the caller's main
module and dies when that is standard input, ``-c``, a notebook or an embedding program): it is
the same process whatever the caller is.  A crash,
hang or deadlock inside libOpenNI2 (it has several: closing a file device right after opening
it, seeking, unloading with a device open) therefore costs a restart of the reader, never the
service:

* every :meth:`OpenNI2Source.read` waits at most its timeout (:class:`FrameTimeout`);
* a reader that dies is seen at once (its pidfd, or its end of the socket closing), and what it
  wrote last on stderr is kept for the message; one that stops answering for
  ``stall_timeout`` seconds is killed.  Either way it is restarted (``stats.restarts``);
* a live camera that stops delivering frames for ``lost_after`` seconds, or whose reader died,
  raises :class:`DeviceLost` once; the following reads reconnect with exponential backoff
  (0.5 s doubling to 10 s) and raise :class:`DeviceLost` while the camera is still missing;
* a recording is resumed after a reader crash at the next frame (frames before it are skipped
  in the new reader, not delivered twice); a recording that crashes the reader three times
  without progress is reported as a corrupt file (:class:`DepthFileError`).

Live cameras: the first one (``openni2://``) or one chosen by URI or serial number
(``openni2://<serial-or-uri>``); ``openni2://Oz`` opens OpenNI's DummyDevice (a synthetic
320x240 stream, for tests).  The depth mode nearest to 640x480 @ 30 fps in 1 mm units is chosen
(the choice is logged when it differs).  Frames carry the device's timestamps and frame
numbers; gaps in the numbers are counted in ``stats.dropped``.

Recordings (``oni:file.oni``) play frame by frame in lockstep (playback speed -1, repeat off):
no frame is dropped however slow the consumer, and :meth:`OpenNI2Source.read` returns ``None``
after the last one.  ``oni:file.oni?loop=1&rate=auto`` plays one like a camera instead: again
from the start after the last frame (indices and timestamps keep increasing) and paced at the
recording's fps (``rate=30`` for a given rate).  The file is checked with :func:`hw.oni.read_oni_header` first, so a missing
or corrupt file raises :class:`DepthFileError` before the native player sees it.

Debian's ``libopenni2-0`` ships drivers for PrimeSense / Asus Xtion (PS1080) cameras.  A
Kinect v1 needs libfreenect's OpenNI2 driver (``libFreenectDriver.so``), built from source and
copied into the OpenNI2 ``Drivers`` folder.
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
import math
import mmap
import multiprocessing.connection
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
import weakref
from multiprocessing import shared_memory
from pathlib import Path
from typing import Any

import numpy as np
import openni.openni2  # noqa: F401  -- the binding (pure Python; the native library loads in the reader)

from hw.backoff import Backoff
from hw.depth import DepthFrame, DepthSource, Intrinsics
from hw.errors import (
    ArgumentError,
    BackendUnavailable,
    DepthFileError,
    DeviceError,
    DeviceLost,
    DeviceNotFound,
    FrameTimeout,
    HwError,
    UriError,
)
from hw.oni import intrinsics_from_fov, read_oni_header
from hw.options import Pacer, flag, positive

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
    a per-user folder in the temp directory when that cannot be written).  Raises :class:`BackendUnavailable` naming the
    package to install when the library is missing.
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
    if status.st_uid != os.getuid() or status.st_mode & 0o022 or not folder.is_dir() or folder.is_symlink():
        folder = Path(tempfile.mkdtemp(prefix="robot-change-openni2-"))  # someone else's: don't trust it
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
def _child_main(conn: multiprocessing.connection.Connection, spec: dict[str, Any]) -> None:
    """Entry point of the reader process.  Messages to the parent: ``("ready", info)``,
    ``("frame", slot, index, timestamp_us)``, ``("end",)``, ``("lost", text)``,
    ``("error", kind, text)``, ``("devices", list)``.  From the parent: ``("shm", name, slots)``,
    ``("free", slot)``, ``("stop",)``, ``("simulate_loss",)``."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's business
    try:
        from openni import _openni2 as c_api
        from openni import openni2
        openni2.initialize(spec["lib_dir"])
    except Exception as exc:  # noqa: BLE001 -- anything here means the library is unusable
        conn.send(("error", "backend", f"libOpenNI2 could not be initialised from {spec['lib_dir']}: {exc}"))
        os._exit(3)
    try:
        if spec["kind"] == "list":
            conn.send(("devices", _child_list_devices(openni2, c_api)))
            os._exit(0)
        _ChildReader(conn, spec, openni2, c_api).run()
    except _ChildExit as done:
        os._exit(done.code)
    except Exception as exc:  # noqa: BLE001 -- report, then leave without native teardown
        with contextlib.suppress(Exception):
            conn.send(("error", "internal", f"OpenNI2 reader failed: {type(exc).__name__}: {exc}"))
        os._exit(4)
    os._exit(0)


def _attach_ring(name: str, size: int) -> mmap.mmap:
    """The parent's shared-memory ring, mapped without multiprocessing's resource tracker (which
    in a process not started by multiprocessing would unlink the parent's segment at exit)."""
    fd = os.open(os.path.join("/dev/shm", name.lstrip("/")), os.O_RDWR)
    try:
        return mmap.mmap(fd, size)
    finally:
        os.close(fd)


#: What the reader process runs: read sys.path and the spec from the socket, then the reader.
_BOOT = """\
import sys
from multiprocessing.connection import Connection
conn = Connection(int(sys.argv[1]))
path, spec = conn.recv()
sys.path[:0] = [p for p in path if p not in sys.path]
from hw.openni2 import _child_main
_child_main(conn, spec)
"""


class _Reader:
    """A reader process: a fresh interpreter running :func:`_child_main`, a connection to it,
    and what it wrote on stderr (kept in a temporary file, so a chatty driver never blocks it).
    In its own session, so a Ctrl-C at the terminal goes to the caller, which stops it."""

    def __init__(self, spec: dict[str, Any]) -> None:
        ours, theirs = socket.socketpair()
        self._stderr = tempfile.TemporaryFile()
        try:
            self._popen = subprocess.Popen(
                [sys.executable, "-c", _BOOT, str(theirs.fileno())], pass_fds=(theirs.fileno(),),
                stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=self._stderr,
                start_new_session=True)
        except OSError as exc:
            self._stderr.close()
            ours.close()
            raise BackendUnavailable(f"cannot start the OpenNI2 reader ({sys.executable!r}: "
                                     f"{exc.strerror or exc})") from None
        finally:
            theirs.close()
        self.pid = self._popen.pid
        self.conn = multiprocessing.connection.Connection(ours.detach())
        try:
            self._pidfd: int | None = os.pidfd_open(self.pid)
        except (AttributeError, OSError):  # not Linux >= 5.3: the socket closing tells
            self._pidfd = None
        # a reader outlives no caller that forgets to close its source
        self._finalizer = weakref.finalize(self, _Reader._end, self._popen)
        self.conn.send((list(sys.path), spec))

    @staticmethod
    def _end(popen: subprocess.Popen) -> None:
        if popen.poll() is None:
            popen.kill()
            with contextlib.suppress(subprocess.TimeoutExpired):
                popen.wait(2.0)

    def receive(self, timeout: float) -> tuple[tuple | None, bool]:
        """Wait up to ``timeout`` s: (message, False); (None, False) when nothing came; (None,
        True) when the reader died (its pidfd fired or the socket closed)."""
        waitables: list[Any] = [self.conn] + ([self._pidfd] if self._pidfd is not None else [])
        ready = multiprocessing.connection.wait(waitables, timeout)
        if self.conn in ready:
            try:
                return self.conn.recv(), False
            except (EOFError, OSError):
                pass
        return None, bool(ready)

    @property
    def exitcode(self) -> int | None:
        """Its exit status (negative: the signal that ended it); None while it runs."""
        return self._popen.poll()

    def join(self, timeout: float) -> None:
        with contextlib.suppress(subprocess.TimeoutExpired):
            self._popen.wait(timeout)

    def is_alive(self) -> bool:
        return self._popen.poll() is None

    def kill(self) -> None:
        with contextlib.suppress(ProcessLookupError):
            self._popen.kill()

    def last_error(self) -> str:
        """The last line the reader wrote on stderr ("" when none)."""
        with contextlib.suppress(Exception):
            self._stderr.flush()
            self._stderr.seek(0, os.SEEK_END)
            size = self._stderr.tell()
            self._stderr.seek(max(0, size - 4096))
            lines = [line.strip() for line in
                     self._stderr.read().decode(errors="replace").splitlines() if line.strip()]
            return lines[-1][:300] if lines else ""
        return ""

    def describe_exit(self) -> str:
        """How it ended, with its last line on stderr when there is one."""
        self.join(0.5)
        how = _describe_exit(self.exitcode)
        last = self.last_error()
        return f"{how} (its last error output: {last})" if last else how

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.conn.close()
        if self._pidfd is not None:
            with contextlib.suppress(OSError):
                os.close(self._pidfd)
            self._pidfd = None
        with contextlib.suppress(Exception):
            self._stderr.close()
        self._finalizer.detach()


class _ChildExit(Exception):
    def __init__(self, code: int) -> None:
        super().__init__(code)
        self.code = code


def _child_list_devices(openni2: Any, c_api: Any) -> list[dict[str, Any]]:
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


class _ChildReader:
    """Opens the device or file, then feeds frames into the shared ring while credits last."""

    def __init__(self, conn: multiprocessing.connection.Connection, spec: dict[str, Any],
                 openni2: Any, c_api: Any) -> None:
        self.conn, self.spec, self.ni, self.c_api = conn, spec, openni2, c_api
        self.is_file = spec["kind"] == "file"
        self.device: Any = None
        self.stream: Any = None
        self.free: set[int] = set()
        self.ring: np.ndarray | None = None
        self.shm: mmap.mmap | None = None
        self.stopped_stream = False

    # --- setup ----------------------------------------------------------------------------
    def run(self) -> None:
        info = self._open_file() if self.is_file else self._open_device()
        self.conn.send(("ready", info))
        msg = self.conn.recv()
        if msg[0] != "shm":
            raise _ChildExit(0)
        _, name, slots = msg
        w, h = info["width"], info["height"]
        self.shm = _attach_ring(name, slots * h * w * 2)
        self.ring = np.ndarray((slots, h * w), dtype=np.uint16, buffer=self.shm)
        self.free = set(range(slots))
        self.width, self.height = w, h
        self.scale_100um = info["pixel_format"] == _PIXEL_FORMAT_100_UM
        self.frames_total = int(info.get("frames") or self.spec.get("frames") or 0)
        self.stream.start()
        self._loop()

    def _fail(self, kind: str, text: str) -> None:
        self.conn.send(("error", kind, text))
        raise _ChildExit(2)

    def _open_file(self) -> dict[str, Any]:
        path = self.spec["target"]
        try:
            self.device = self.ni.Device(os.fsencode(path))
            self.device.playback.set_speed(-1.0)  # manual: one frame per read, none dropped
            # looping: the player starts again after the last frame (indices keep counting)
            self.device.playback.set_repeat_enabled(bool(self.spec.get("loop")))
            self.stream = self.device.create_depth_stream()
        except Exception as exc:  # noqa: BLE001
            self._fail("file", f"OpenNI2 cannot play {path}: {exc}")
        if self.stream is None:
            self._fail("file", f"recording {path} holds no depth stream")
        mode = self.stream.get_video_mode()
        if mode.pixelFormat not in (_PIXEL_FORMAT_1_MM, _PIXEL_FORMAT_100_UM):
            self._fail("file", f"recording {path} holds depth in pixel format {mode.pixelFormat}, "
                               "not millimetres (DEPTH_1_MM)")
        return {
            "width": mode.resolutionX, "height": mode.resolutionY, "fps": mode.fps,
            "pixel_format": int(mode.pixelFormat), "frames": int(self.stream.get_number_of_frames()),
            **self._fov(), "uri": path, "vendor": "", "name": "recording", "serial": None,
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
                self._fail("not_found", "no OpenNI2 depth camera is connected. " + _NO_CAMERA_HINT)
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
            self._fail("not_found", f"no OpenNI2 camera with URI or serial number {target!r} "
                                    f"(connected: {present}{open_error}). " + _NO_CAMERA_HINT)
        self.device = device
        info = device.get_device_info()
        sensor = device.get_sensor_info(self.ni.SENSOR_DEPTH)
        if sensor is None:
            self._fail("not_found", f"camera {target!r} has no depth sensor")
        depth_formats = (_PIXEL_FORMAT_1_MM, _PIXEL_FORMAT_100_UM)
        modes = [m for m in sensor.videoModes if int(m.pixelFormat) in depth_formats]
        if not modes:
            self._fail("not_found", f"camera {target!r} offers no depth mode in millimetres")
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
            unit = "1 mm" if int(mode.pixelFormat) == _PIXEL_FORMAT_1_MM else "100 um (converted to mm)"
            note = (f"camera {target!r} does not offer 640x480 @ 30 fps in 1 mm; using the nearest "
                    f"mode {mode.resolutionX}x{mode.resolutionY} @ {mode.fps} fps, {unit}")
        return {
            "width": mode.resolutionX, "height": mode.resolutionY, "fps": mode.fps,
            "pixel_format": int(mode.pixelFormat), **self._fov(),
            "uri": info.uri.decode(errors="replace"), "vendor": info.vendor.decode(errors="replace"),
            "name": info.name.decode(errors="replace"), "serial": _serial_of(device, self.c_api),
            "mode_note": note,
        }

    # --- streaming ------------------------------------------------------------------------
    def _handle(self, msg: tuple) -> None:
        if msg[0] == "free":
            self.free.add(msg[1])
        elif msg[0] == "stop":
            self._shutdown()
        elif msg[0] == "simulate_loss":  # test hook: the camera stops sending, as when unplugged
            self.stream.stop()
            self.stopped_stream = True

    def _drain(self, wait: float = 0.0) -> None:
        if self.conn.poll(wait):
            while True:
                self._handle(self.conn.recv())
                if not self.conn.poll(0):
                    break

    def _shutdown(self) -> None:
        # Live cameras are stopped properly; a file device is left to the OS (closing one can
        # crash libOpenNI2, and there is nothing to release).
        if not self.is_file:
            with contextlib.suppress(Exception):
                if not self.stopped_stream:
                    self.stream.stop()
                self.stream.close()
                self.device.close()
        raise _ChildExit(0)

    def _loop(self) -> None:
        ni = self.ni
        skip = int(self.spec.get("skip", 0))  # frames a previous reader already delivered
        loop = bool(self.spec.get("loop")) and self.is_file
        lap_us = int(self.spec.get("lap_us") or 0)  # a looped recording's time per lap
        played = 0
        silence_limit = float(self.spec["stall_timeout" if self.is_file else "lost_after"])
        # a camera may take a few seconds for its first frame
        last_frame = time.monotonic() + (0.0 if self.is_file else max(0.0, 5.0 - silence_limit))
        pixels = self.width * self.height
        while True:
            self._drain(0.0 if (self.free or not self.is_file) else 0.1)
            if self.is_file and not self.free:
                last_frame = time.monotonic()  # waiting for the consumer is not a stall
                continue
            try:
                ready = ni.wait_for_any_stream([self.stream], 0.05)
            except Exception:  # noqa: BLE001 -- a stopped or vanished stream
                time.sleep(0.05)
                ready = None
            now = time.monotonic()
            if ready is None:
                if now - last_frame > silence_limit:
                    if self.is_file:
                        self._fail("file", f"the OpenNI2 player delivered no frame for "
                                           f"{silence_limit:.1f} s (the recording may be corrupt)")
                    self.conn.send(("lost", f"the camera sent no frame for {silence_limit:.1f} s "
                                            "(unplugged or USB reset?)"))
                    raise _ChildExit(5)
                continue
            last_frame = now
            frame = self.stream.read_frame()
            try:
                raw = frame._frame
                index, stamp = int(raw.frameIndex), int(raw.timestamp)
                played += 1
                if loop and self.frames_total:  # later laps continue the count and the clock
                    lap = (played - 1) // self.frames_total
                    index, stamp = played, stamp + lap * lap_us
                if self.is_file and played <= skip:
                    continue
                if not self.free:
                    continue  # live camera, consumer behind: this frame is dropped
                if raw.width != self.width or raw.height != self.height or raw.dataSize < pixels * 2:
                    self._fail("file" if self.is_file else "internal",
                               f"frame {index} is {raw.width}x{raw.height} ({raw.dataSize} bytes), "
                               f"expected {self.width}x{self.height}")
                row = raw.stride // 2 if raw.stride else self.width
                src = np.ctypeslib.as_array(ctypes.cast(raw.data, ctypes.POINTER(ctypes.c_uint16)),
                                            shape=(self.height * row,))
                slot = self.free.pop()
                assert self.ring is not None
                if row == self.width and not self.scale_100um:
                    self.ring[slot] = src
                else:
                    image = src.reshape(self.height, row)[:, : self.width]
                    self.ring[slot] = (image // 10 if self.scale_100um else image).ravel()
            finally:
                frame.close()
            self.conn.send(("frame", slot, index, stamp))
            if self.is_file and not loop and self.frames_total and played >= self.frames_total:
                self.conn.send(("end",))
                while True:  # wait for "stop"; frees are irrelevant now
                    try:
                        msg = self.conn.recv()
                    except EOFError:
                        raise _ChildExit(0) from None
                    self._handle(msg)


# =================================================================================================
# the parent side
# =================================================================================================
class OpenNI2Source(DepthSource):
    """A depth source read through OpenNI2 in a child process.  Use :func:`open_device` or
    :func:`open_recording` (or :func:`hw.depth.open_depth`) to make one.

    Options: ``slots`` (frames buffered ahead, default 4), ``start_timeout`` (s to open the
    device in the reader, 10), ``stall_timeout`` (s of silence from a reader before it is
    killed and restarted, 5), ``lost_after`` (s without a camera frame before the camera counts
    as lost, 2), ``max_restarts`` (reader crashes without progress before a recording counts as
    corrupt, 3).  Recordings only: ``loop`` (start again after the last frame, for ever; frame
    indices and timestamps keep increasing across laps, so a daemon fed by a recording runs like
    one fed by a camera) and ``rate`` (frames per second to pace delivery at, like a camera;
    ``"auto"`` for the recording's own fps; default: as fast as they are read).
    """

    def __init__(self, kind: str, target: str, *, slots: int = 4, start_timeout: float = 10.0,
                 stall_timeout: float = 5.0, lost_after: float = 2.0, max_restarts: int = 3,
                 loop: bool = False, rate: float | str | None = None) -> None:
        super().__init__()
        if kind not in ("file", "device"):
            raise ArgumentError(f"kind must be 'file' or 'device', not {kind!r}")
        if kind != "file" and (loop or rate is not None):
            raise UriError("the loop and rate options are for recordings (oni:FILE.oni); a live "
                           "camera runs at its own rate")
        self.kind = kind
        self.target = target
        self.uri = f"oni:{target}" if kind == "file" else f"openni2://{target}"
        self.slots = int(slots)
        self.start_timeout = float(start_timeout)
        self.stall_timeout = float(stall_timeout)
        self.lost_after = float(lost_after)
        self.max_restarts = int(max_restarts)
        if self.slots < 1 or min(self.start_timeout, self.stall_timeout, self.lost_after) <= 0:
            raise ArgumentError("slots must be >= 1 and the timeouts > 0")
        #: What the reader reported when it opened the source (uri, vendor, name, serial, mode).
        self.info: dict[str, Any] = {}
        self._intrinsics: Intrinsics | None = None
        self._proc: _Reader | None = None
        self._conn: multiprocessing.connection.Connection | None = None
        self._shm: shared_memory.SharedMemory | None = None
        self._ring: np.ndarray | None = None
        self._open = False
        self._ended = False
        self._last_index: int | None = None
        self._delivered = 0
        self._last_heard = 0.0
        self._restart_due: float | None = None  # live: when to try reconnecting
        self._backoff = Backoff(0.5, 10.0)
        self._failed_restarts = 0
        self.loop = bool(loop)
        if kind == "file":
            self._header = read_oni_header(target)
            self._intrinsics = self._header.intrinsics()
            if rate in ("auto", "fps"):
                rate = float(self._header.fps)
        if rate is not None and not (isinstance(rate, (int, float)) and math.isfinite(rate)
                                     and rate > 0):
            raise UriError(f"OpenNI2 option rate={rate!r}: frames per second > 0, or 'auto' for "
                           "the recording's own fps")
        self.rate = None if rate is None else float(rate)
        self._pacer = Pacer(self.rate)

    # --- DepthSource ---------------------------------------------------------------------------
    @property
    def intrinsics(self) -> Intrinsics:
        """Intrinsics from the stream's field of view (OpenNI's VGA defaults when the driver
        reports none).  Known for a recording at once, for a camera once it is open."""
        if self._intrinsics is None:
            raise DeviceError(f"{self.uri}: open the camera before asking for its intrinsics")
        return self._intrinsics

    @property
    def pid(self) -> int | None:
        """Process id of the current reader (``None`` when none runs)."""
        return self._proc.pid if self._proc is not None else None

    def open(self) -> None:
        """Start the reader and open the camera or recording.  Raises :class:`DeviceNotFound`,
        :class:`DepthFileError` or :class:`BackendUnavailable` with what to do."""
        if self._open:
            return
        if self.kind == "file":
            self._header = read_oni_header(self.target)
        self._lib_dir = library_dir()
        self._ended = False
        self._last_index = None
        self._pacer.reset()
        self._delivered = 0  # frames of this opening (a restarted reader skips them)
        self._start_reader(skip=0)
        self._open = True

    def close(self) -> None:
        """Stop the reader and release the camera.  Safe to call more than once."""
        self._open = False
        self._stop_reader()
        if self._shm is not None:
            self._ring = None
            with contextlib.suppress(Exception):
                self._shm.close()
            with contextlib.suppress(Exception):
                self._shm.unlink()
            self._shm = None

    def read(self, timeout: float | None = 1.0) -> DepthFrame | None:
        """The next frame, waiting at most ``timeout`` s (``None``: as long as it takes);
        ``None`` after a recording's last frame.

        Raises :class:`FrameTimeout` when no frame came in time, :class:`DeviceLost` when the
        camera (or its reader) is gone -- later reads reconnect -- and :class:`DepthFileError`
        when a recording cannot be played on.  A reader silent for ``stall_timeout`` s is
        killed: a recording's is replaced at once when ``timeout`` is ``None`` (else on the next
        read, after a :class:`FrameTimeout`); a camera's counts as a lost camera.
        """
        if not self._open:
            raise DeviceError(f"{self.uri}: the source is not open; use it in a 'with' block or call open()")
        if self._ended:
            return None
        deadline = math.inf if timeout is None else time.monotonic() + max(0.0, float(timeout))
        self._pacer.wait(timeout, f"{self.uri} (option rate)")
        if self._proc is None:
            self._reconnect(deadline)
        while True:
            remaining = max(0.0, deadline - time.monotonic())
            msg, died = self._receive(min(remaining, 0.25))
            if msg is not None:
                self._last_heard = time.monotonic()
                result = self._on_message(msg)
                if result is not None or self._ended:
                    return result
                continue
            if died:  # the reader died (sentinel fired or pipe closed)
                self._on_reader_death(self._describe_death())
                # a recording resumes in a new reader: give it a moment for the next frame
                deadline = max(deadline, time.monotonic() + 1.0)
                continue
            silent = time.monotonic() - self._last_heard
            if silent > self.stall_timeout:
                pid = self._proc.pid
                why = f"(pid {pid}) stopped answering for {silent:.1f} s"
                if self.kind == "file" and timeout is None:
                    self._on_reader_death(why)
                    continue
                self._stop_reader(kill=True)
                self._schedule_restart()
                if self.kind == "file":
                    raise FrameTimeout(f"{self.uri}: the OpenNI2 reader {why}; it was killed and "
                                       "will be restarted")
                raise DeviceLost(f"{self.uri}: the OpenNI2 reader {why}; it was killed, reconnecting")
            if time.monotonic() >= deadline:
                raise FrameTimeout(f"{self.uri}: no depth frame within {timeout:.2f} s")

    # --- test hooks ----------------------------------------------------------------------------
    def simulate_device_loss(self) -> None:
        """Make the reader stop the camera's stream, as if it had been unplugged (for tests of
        the recovery path)."""
        if self._conn is not None:
            self._conn.send(("simulate_loss",))

    # --- internals -----------------------------------------------------------------------------
    def _on_message(self, msg: tuple) -> DepthFrame | None:
        kind = msg[0]
        if kind == "frame":
            _, slot, index, stamp = msg
            assert self._ring is not None and self._conn is not None
            height, width = self._shape
            depth = self._ring[slot].reshape(height, width).copy()
            with contextlib.suppress(OSError):
                self._conn.send(("free", slot))
            if self._last_index is not None and index > self._last_index + 1:
                self.stats.dropped += index - self._last_index - 1
            self._last_index = index
            self._failed_restarts = 0
            self._delivered += 1
            self.stats.delivered += 1
            assert self._intrinsics is not None
            return DepthFrame(depth, int(stamp), int(index), self._intrinsics)
        if kind == "end":
            self._ended = True
            self._stop_reader()
            return None
        if kind == "lost":
            self._stop_reader(kill=True)
            self._schedule_restart()
            raise DeviceLost(f"{self.uri}: {msg[1]}; reconnecting")
        if kind == "error":
            self._stop_reader(kill=True)
            raise self._error(msg[1], msg[2])
        return None

    def _error(self, kind: str, text: str) -> HwError:
        if kind == "not_found":
            return DeviceNotFound(text)
        if kind == "file":
            return DepthFileError(text)
        if kind == "backend":
            return BackendUnavailable(text + "; reinstall libopenni2-0 and the 'openni' binding")
        return DeviceError(f"{self.uri}: {text}")

    def _schedule_restart(self) -> None:
        self._restart_due = time.monotonic()

    def _describe_death(self) -> str:
        return self._proc.describe_exit() if self._proc is not None else _describe_exit(None)

    def _on_reader_death(self, how: str) -> None:
        """The reader died or hung (``how``): a recording continues in a new reader, skipping
        the frames already delivered; a camera raises :class:`DeviceLost` and reconnects later."""
        self._stop_reader(kill=True)
        if self.kind == "file":
            self._failed_restarts += 1
            if self._failed_restarts > self.max_restarts:
                raise DepthFileError(
                    f"{self.uri}: the OpenNI2 player failed {self._failed_restarts} times after "
                    f"frame {self._last_index or 0} (its reader {how}); the recording is probably "
                    "corrupt (crashed player)"
                )
            log.warning("%s: OpenNI2 reader %s; restarting at frame %s", self.uri, how,
                        (self._last_index or 0) + 1)
            self.stats.restarts += 1
            self._start_reader(skip=self._delivered)
            return
        self._schedule_restart()
        raise DeviceLost(f"{self.uri}: the OpenNI2 reader {how}; reconnecting")

    def _reconnect(self, deadline: float) -> None:
        """Start a new reader after a loss (live: with backoff; file: at once)."""
        if self.kind == "file":
            self.stats.restarts += 1
            self._start_reader(skip=self._delivered)
            return
        due = self._restart_due if self._restart_due is not None else time.monotonic()
        wait = due - time.monotonic()
        if wait > 0:
            if wait > deadline - time.monotonic():
                time.sleep(max(0.0, deadline - time.monotonic()))
                raise DeviceLost(f"{self.uri}: camera lost; next reconnection attempt in "
                                 f"{max(0.0, due - time.monotonic()):.1f} s")
            time.sleep(wait)
        try:
            self._start_reader(skip=0)
        except (DeviceNotFound, DeviceError) as exc:
            self._restart_due = time.monotonic() + self._backoff.next()
            raise DeviceLost(f"{self.uri}: camera still missing ({exc}); next attempt in "
                             f"{self._restart_due - time.monotonic():.1f} s") from exc
        self.stats.restarts += 1
        self._backoff.reset()
        self._restart_due = None
        self._last_index = None  # a reconnected camera counts its frames from the start again

    def _start_reader(self, skip: int) -> None:
        """Start a reader process and wait until it has opened the source; ``skip``: frames of
        a recording to pass over (already delivered by a previous reader)."""
        lap_us = 0
        if self.kind == "file":
            header = self._header
            lap_us = (header.last_timestamp_us - header.first_timestamp_us
                      + round(1e6 / max(header.fps, 1)))
        spec = {"kind": self.kind, "target": self.target, "lib_dir": self._lib_dir,
                "skip": skip, "frames": self._header.frames if self.kind == "file" else 0,
                "loop": self.loop, "lap_us": lap_us,
                "stall_timeout": self.stall_timeout, "lost_after": self.lost_after}
        proc = _Reader(spec)
        self._proc, self._conn = proc, proc.conn
        try:
            info = self._await_ready()
        except BaseException:
            self._stop_reader(kill=True)
            raise
        self.info = info
        width, height = int(info["width"]), int(info["height"])
        self._shape = (height, width)
        self._intrinsics = intrinsics_from_fov(width, height, info.get("hfov"), info.get("vfov"))
        if info.get("mode_note"):
            log.warning("%s", info["mode_note"])
        need = self.slots * width * height * 2
        if self._shm is None or self._shm.size < need:
            if self._shm is not None:
                self._ring = None
                with contextlib.suppress(Exception):
                    self._shm.close()
                    self._shm.unlink()
            self._shm = shared_memory.SharedMemory(create=True, size=need)
        self._ring = np.ndarray((self.slots, width * height), dtype=np.uint16, buffer=self._shm.buf)
        proc.conn.send(("shm", self._shm.name, self.slots))
        self._last_heard = time.monotonic()

    def _await_ready(self) -> dict[str, Any]:
        deadline = time.monotonic() + self.start_timeout
        while True:
            msg, died = self._receive(max(0.0, deadline - time.monotonic()))
            if msg is not None:
                if msg[0] == "ready":
                    return msg[1]
                if msg[0] == "error":
                    raise self._error(msg[1], msg[2])
                continue
            if died:
                assert self._proc is not None
                how = self._proc.describe_exit()
                if self.kind == "file":
                    raise DepthFileError(f"{self.uri}: the OpenNI2 player {how} while opening the "
                                         "recording (its .oni header was checked and is valid)")
                raise DeviceError(f"{self.uri}: the OpenNI2 reader {how} while opening the camera")
            raise DeviceError(f"{self.uri}: the OpenNI2 reader did not open the "
                              f"{'recording' if self.kind == 'file' else 'camera'} within "
                              f"{self.start_timeout:.0f} s")

    def _receive(self, timeout: float) -> tuple[tuple | None, bool]:
        assert self._proc is not None
        return self._proc.receive(timeout)

    def _stop_reader(self, kill: bool = False) -> None:
        proc, conn = self._proc, self._conn
        self._proc = self._conn = None
        if conn is not None:
            if not kill:
                with contextlib.suppress(Exception):
                    conn.send(("stop",))
            with contextlib.suppress(Exception):
                conn.close()
        if proc is not None:
            if not kill:
                proc.join(1.0)
            if proc.is_alive():
                proc.kill()  # SIGKILL also ends a stopped (SIGSTOP) or hung reader
                proc.join(2.0)
            with contextlib.suppress(Exception):
                proc.close()


def _describe_exit(code: int | None) -> str:
    if code is None:
        return "stopped answering"
    if code < 0:
        try:
            name = signal.Signals(-code).name
        except ValueError:
            name = f"signal {-code}"
        return f"was killed by {name}"
    return f"exited with status {code}"


# =================================================================================================
# factories, device list, recording
# =================================================================================================
def _options(options: dict[str, Any]) -> dict[str, Any]:
    """URI query options arrive as strings; convert the known ones."""
    kinds = {"slots": int, "start_timeout": float, "stall_timeout": float, "lost_after": float,
             "max_restarts": int, "loop": lambda v: flag("OpenNI2", "loop", v), "rate": _rate}
    out = {}
    for key, value in options.items():
        if key not in kinds:
            raise UriError(f"unknown OpenNI2 option {key!r}; known: {', '.join(sorted(kinds))}")
        if key in ("loop", "rate"):
            out[key] = kinds[key](value)
            continue
        try:
            out[key] = kinds[key](value)
        except (TypeError, ValueError):
            raise UriError(f"OpenNI2 option {key}={value!r} must be a number") from None
    return out


def _rate(value: Any) -> float | str | None:
    if value is None or value == "":
        return None
    if isinstance(value, str) and value.strip().lower() in ("auto", "fps"):
        return "auto"
    return positive("OpenNI2", "rate", value, "frames per second, or 'auto' for the "
                    "recording's own fps")


def open_device(target: str = "", **options: Any) -> OpenNI2Source:
    """A live camera: ``""`` for the first one, else a URI or serial number (``"Oz"`` is the
    DummyDevice).  Returned unopened."""
    return OpenNI2Source("device", target.strip().strip("/"), **_options(options))


def open_recording(target: str, **options: Any) -> OpenNI2Source:
    """An ``.oni`` recording, played frame by frame.  Raises :class:`DepthFileError` at once for
    a missing or corrupt file.  Returned unopened."""
    return OpenNI2Source("file", str(Path(target).expanduser()), **_options(options))


def list_devices(timeout: float = 10.0) -> list[dict[str, Any]]:
    """The connected OpenNI2 cameras: dicts with ``uri``, ``vendor``, ``name``, ``usb_vendor_id``,
    ``usb_product_id`` and ``serial`` when the driver reports one.  Empty when none is plugged
    in.  Enumerated in a child process, like everything native."""
    lib_dir = library_dir()
    proc = _Reader({"kind": "list", "lib_dir": lib_dir})
    try:
        msg, died = proc.receive(timeout)
        if msg is None and not died:
            raise DeviceError(f"listing OpenNI2 cameras took more than {timeout:.0f} s (a driver hangs?)")
        if msg is None:
            raise DeviceError(f"the OpenNI2 reader {proc.describe_exit()} while listing cameras")
        if msg[0] == "error":
            raise BackendUnavailable(msg[2]) if msg[1] == "backend" else DeviceError(msg[2])
        return list(msg[1])
    finally:
        proc.join(2.0)
        if proc.is_alive():
            proc.kill()
            proc.join(1.0)
        proc.close()


__all__ = ["OpenNI2Source", "library_dir", "list_devices", "open_device", "open_recording"]
