"""Intel RealSense depth backend: live D4xx cameras and RealSense recordings, through librealsense
(``pyrealsense2``, the ``realsense`` extra).

    open_depth("realsense://")                      # the first RealSense camera
    open_depth("realsense://123622270300?resolution=848x480&fps=30&preset=high_accuracy")
    open_depth("realsense:run.db3")                 # a recording, frame by frame
    open_depth("realsense:run.db3?loop=1&rate=auto")   # ... played like a camera

librealsense runs in a supervised reader process (:mod:`hw.supervised`), as OpenNI2 does: a
crash or hang inside it costs a restart of the reader, never the service; every read has a
timeout; a camera that stops is :class:`DeviceLost` and reconnects with the one back-off; a
recording resumes at its next frame.

Live: depth in Z16 at ``resolution`` (``640x480`` by default, or ``848x480``, the D4xx's native
width, ...) and ``fps`` (30), the emitter on (``emitter=0`` turns it off), an optional
``preset`` (the D4xx visual presets: ``default``, ``high_accuracy``, ``high_density``,
``medium_density``, ``hand``, ``remove_ir_pattern``).  Samples are converted to millimetres
from the sensor's depth units (D400: 1 mm by default; a D405 sends 0.1 mm).  Intrinsics are
the depth stream's own (its distortion model and coefficients are in ``info``; a D4xx's depth
stream is rectified).

Recordings: what librealsense's recorder writes (``rs-record``, the RealSense Viewer,
``rs.config.enable_record_to_file``, :func:`hw.realsense_record.write_realsense_recording`):
a ROS 2 ``.db3`` (librealsense 2.59 and later) or a ROS 1 ``.bag`` (earlier ones), played in
lockstep (none dropped).  The file is checked through :mod:`hw.rosbag`'s reader first, so a
missing, truncated or foreign file is a :class:`DepthFileError` before librealsense sees it.
Without librealsense, the bag backend reads the same ``.db3`` (``rosbag:run.db3``) and gives
the same frames.
"""

from __future__ import annotations

import contextlib
import importlib.util
import re
from pathlib import Path
from typing import Any

import numpy as np

from hw.depth import Intrinsics
from hw.errors import BackendUnavailable, DepthFileError, FrameError, UriError
from hw.options import flag, positive
from hw.realsense_bag import DEPTH_TOPIC, float32_decimal, stream_fps, to_millimetres
from hw.rosbag import open_bag
from hw.supervised import (
    ChildFailure,
    FrameFeed,
    SupervisedSource,
    ask_reader,
    reader_main,
    source_options,
)

__all__ = ["PRESETS", "RealSenseSource", "list_devices", "open_realsense"]

#: The D4xx visual presets by the names the option takes (rs.rs400_visual_preset).
PRESETS = ("custom", "default", "hand", "high_accuracy", "high_density", "medium_density",
           "remove_ir_pattern")
_NO_CAMERA_HINT = ("Check the USB 3 cable and port (a D4xx on USB 2 offers fewer modes) and "
                   "that the user may access the camera (librealsense's udev rules, "
                   "99-realsense-libusb.rules).")
_RECORDING_SUFFIXES = (".db3", ".bag")


# =================================================================================================
# the reader process (everything native happens here)
# =================================================================================================
def reader_entry(conn: Any, spec: dict[str, Any]) -> None:
    """What the reader process runs (:func:`hw.supervised.reader_main` with librealsense)."""
    reader_main(conn, spec, _RealSenseFeed, _child_list_devices)


def _library() -> Any:
    try:
        import pyrealsense2 as rs
    except Exception as exc:  # noqa: BLE001 -- anything here means the library is unusable
        raise ChildFailure("backend", f"pyrealsense2 cannot be imported ({exc})") from None
    return rs


def _child_list_devices(spec: dict[str, Any]) -> list[dict[str, Any]]:
    rs = _library()
    found = []
    for device in rs.context().query_devices():
        entry = {}
        for key, info in (("name", rs.camera_info.name), ("serial", rs.camera_info.serial_number),
                          ("firmware", rs.camera_info.firmware_version),
                          ("usb", rs.camera_info.usb_type_descriptor),
                          ("product_line", rs.camera_info.product_line)):
            with contextlib.suppress(Exception):
                if device.supports(info):
                    entry[key] = str(device.get_info(info))
        found.append(entry)
    return found


class _RealSenseFeed(FrameFeed):
    """A RealSense camera or recording through ``rs.pipeline``, in the reader process."""

    def __init__(self, spec: dict[str, Any]) -> None:
        self.rs = _library()
        self.spec = spec
        self.is_file = spec["kind"] == "file"
        self.pipeline: Any = None
        self.config: Any = None

    def open(self) -> dict[str, Any]:
        rs, spec = self.rs, self.spec
        self.pipeline, self.config = rs.pipeline(), rs.config()
        if self.is_file:
            self.config.enable_device_from_file(spec["target"], repeat_playback=bool(spec["loop"]))
        else:
            serial = self._choose_device()
            self.config.enable_device(serial)
            width, height = spec["resolution"]
            self.config.enable_stream(rs.stream.depth, width, height, rs.format.z16, spec["fps"])
        try:
            profile = self.config.resolve(rs.pipeline_wrapper(self.pipeline))
        except RuntimeError as exc:
            if self.is_file:
                raise ChildFailure("file", f"librealsense cannot play {spec['target']}: "
                                           f"{exc}") from None
            width, height = spec["resolution"]
            raise ChildFailure("not_found", f"the RealSense camera offers no {width}x{height} "
                                            f"depth at {spec['fps']} fps ({exc}); choose "
                                            "another resolution / fps") from None
        device = profile.get_device()
        try:
            sensor = device.first_depth_sensor()
        except RuntimeError:
            raise ChildFailure("file" if self.is_file else "not_found",
                               f"{self._what()} has no depth sensor") from None
        if not self.is_file:
            self._set_options(sensor)
        self.units_mm = float(sensor.get_depth_scale()) * 1000.0
        stream = profile.get_stream(rs.stream.depth).as_video_stream_profile()
        camera = stream.get_intrinsics()
        self.width, self.height = int(camera.width), int(camera.height)
        self.buffer = np.empty((self.height, self.width), dtype=np.uint16)
        coeffs = [float(c) for c in camera.coeffs]
        note = ""
        if any(coeffs):
            note = (f"{self._what()}: its depth stream has {camera.model} distortion "
                    f"{coeffs}; it is read as a pinhole image")
        names = {"name": rs.camera_info.name, "serial": rs.camera_info.serial_number,
                 "firmware": rs.camera_info.firmware_version}
        described = {key: (str(device.get_info(info)) if device.supports(info) else None)
                     for key, info in names.items()}
        return {"width": self.width, "height": self.height, "fps": int(stream.fps()),
                "fx": float32_decimal(camera.fx), "fy": float32_decimal(camera.fy),
                "cx": float32_decimal(camera.ppx), "cy": float32_decimal(camera.ppy),
                "distortion": str(camera.model), "coeffs": coeffs,
                "depth_units_m": self.units_mm / 1000.0, "uri": spec["target"],
                "mode_note": note, **described}

    def _what(self) -> str:
        return f"recording {self.spec['target']}" if self.is_file else "the RealSense camera"

    def _choose_device(self) -> str:
        rs, target = self.rs, self.spec["target"]
        serials = []
        for device in rs.context().query_devices():
            with contextlib.suppress(Exception):
                serials.append(str(device.get_info(rs.camera_info.serial_number)))
        if not serials and not target:
            raise ChildFailure("not_found", "no RealSense camera is connected. " + _NO_CAMERA_HINT)
        if not target:
            return serials[0]
        if target not in serials:
            connected = f"connected: {', '.join(serials)}" if serials else "none is connected"
            raise ChildFailure("not_found", f"no RealSense camera with serial number {target!r} "
                                            f"({connected}; a recording is named by its file, "
                                            f"e.g. realsense:{target}.db3). " + _NO_CAMERA_HINT)
        return target

    def _set_options(self, sensor: Any) -> None:
        rs, spec = self.rs, self.spec
        if sensor.supports(rs.option.emitter_enabled):
            sensor.set_option(rs.option.emitter_enabled, 1.0 if spec["emitter"] else 0.0)
        preset = spec.get("preset")
        if preset:
            if not sensor.supports(rs.option.visual_preset):
                raise ChildFailure("not_found", f"the RealSense camera has no visual presets "
                                                f"(asked for {preset!r})")
            value = getattr(rs.rs400_visual_preset, preset)
            sensor.set_option(rs.option.visual_preset, float(int(value)))

    def start(self) -> None:
        profile = self.pipeline.start(self.config)
        if self.is_file:
            profile.get_device().as_playback().set_real_time(False)  # lockstep: none dropped

    def next_frame(self, timeout: float) -> tuple[np.ndarray, int, int] | None:
        try:
            ok, frames = self.pipeline.try_wait_for_frames(max(1, int(timeout * 1000)))
        except RuntimeError:  # a stopped pipeline (simulated loss) or a vanished device
            return None
        if not ok:
            return None
        depth = frames.get_depth_frame()
        if not depth:
            return None
        samples = np.asanyarray(depth.get_data())
        self.buffer[...] = (samples if abs(self.units_mm - 1.0) < 1e-6 else
                            to_millimetres(samples, self.units_mm))
        return self.buffer, int(depth.get_frame_number()), round(depth.get_timestamp() * 1000)

    def simulate_loss(self) -> None:
        with contextlib.suppress(RuntimeError):
            self.pipeline.stop()

    def shutdown(self) -> None:
        with contextlib.suppress(Exception):
            self.pipeline.stop()


# =================================================================================================
# the parent side
# =================================================================================================
class RealSenseSource(SupervisedSource):
    """A RealSense camera or recording read through librealsense in a reader process
    (:mod:`hw.supervised`: options and failures).  Made by :func:`open_realsense` (or
    :func:`hw.depth.open_depth`); ``info`` holds the camera's name, serial, firmware, depth
    units and distortion once open."""

    library = "librealsense"
    reader_module = __name__

    def __init__(self, kind: str, target: str, *, resolution: tuple[int, int] = (640, 480),
                 fps: int = 30, preset: str | None = None, emitter: bool = True,
                 **options: Any) -> None:
        if importlib.util.find_spec("pyrealsense2") is None:  # the reader would fail on it
            raise BackendUnavailable("the RealSense backend needs librealsense's Python binding: "
                                     + self._backend_hint())
        self.resolution, self.fps, self.preset, self.emitter = resolution, fps, preset, emitter
        uri = f"realsense:{target}" if kind == "file" else f"realsense://{target}"
        super().__init__(kind, target, uri, **options)

    def _check_file(self) -> float:
        """The recording's depth frames (from the bag's index) and fps (from its stream info,
        30 when it has none that the bag backend reads)."""
        path = Path(self.target)
        if not path.is_file():
            raise DepthFileError(f"{self.target}: no such file (a RealSense recording is a .db3 "
                                 "or .bag file)")
        if path.suffix.lower() not in _RECORDING_SUFFIXES:
            raise DepthFileError(f"{self.target}: not a RealSense recording by its name (.db3 "
                                 "from librealsense 2.59 on, .bag before)")
        reader = open_bag(path)
        try:
            topics = {name: info.msgcount for name, info in reader.topics.items()
                      if DEPTH_TOPIC.match(name)}
            fps = stream_fps(reader, min(topics, default=""))
        finally:
            reader.close()
        if not topics or not max(topics.values()):
            raise DepthFileError(f"{self.target}: a bag, but not a RealSense recording with depth "
                                 "(no /device_N/sensor_M/Depth_K/image/data topic with messages); "
                                 "read another bag with rosbag:")
        self._frames = max(topics.values())
        return fps

    def _reader_spec(self) -> dict[str, Any]:
        return {"resolution": self.resolution, "fps": self.fps, "preset": self.preset,
                "emitter": self.emitter, "frames": self._frames if self.kind == "file" else 0}

    def _intrinsics_from(self, info: dict[str, Any]) -> Intrinsics:
        try:
            return Intrinsics(int(info["width"]), int(info["height"]), info["fx"], info["fy"],
                              info["cx"], info["cy"])
        except FrameError as exc:
            raise DepthFileError(f"{self.uri}: its depth stream's intrinsics make no pinhole "
                                 f"camera ({exc})") from None

    def _backend_hint(self) -> str:
        return "install the realsense extra (pip install pyrealsense2)"


# =================================================================================================
# factory, device list
# =================================================================================================
def open_realsense(target: str = "", **options: Any) -> RealSenseSource:
    """The ``realsense:`` backend of :func:`hw.depth.open_depth`: a recording when ``target``
    names a file (``.db3`` / ``.bag``), else the camera with that serial number (``""``: the
    first).  Options: ``resolution``, ``fps``, ``preset``, ``emitter`` (cameras); ``loop``,
    ``rate`` (recordings); ``slots``, ``start_timeout``, ``stall_timeout``, ``lost_after``,
    ``max_restarts`` (both).  Returned unopened."""
    target = target.strip()
    # a serial number is letters and digits; anything else, or what exists here, names a file
    is_file = not re.fullmatch(r"[0-9A-Za-z_-]*", target.strip("/")) or \
        (bool(target) and Path(target).exists())
    camera = {"resolution": _resolution, "fps": _fps, "preset": _preset,
              "emitter": lambda value: flag("RealSense", "emitter", value)}
    for key in options:
        if key in camera and is_file:
            raise UriError(f"RealSense option {key} is for a live camera; a recording plays in "
                           "the mode it was recorded in")
    parsed = source_options("RealSense", options, camera)
    if is_file:
        return RealSenseSource("file", str(Path(target).expanduser()), **parsed)
    return RealSenseSource("device", target.strip("/"), **parsed)


def _resolution(value: Any) -> tuple[int, int]:
    if isinstance(value, tuple):
        return value
    match = re.fullmatch(r"\s*(\d{1,5})\s*[xX]\s*(\d{1,5})\s*", str(value))
    if not match or min(int(match.group(1)), int(match.group(2))) < 16:
        raise UriError(f"RealSense option resolution={value!r}: a depth mode's WIDTHxHEIGHT, "
                       "each at least 16 pixels (a D4xx's: 424x240, 480x270, 640x360, 640x480, "
                       "848x480, 1280x720)")
    return int(match.group(1)), int(match.group(2))


def _fps(value: Any) -> int:
    fps = positive("RealSense", "fps", value, "frames per second: 6, 15, 30, 60 or 90 on a D4xx")
    if fps != int(fps):
        raise UriError(f"RealSense option fps={value!r}: a whole number of frames per second")
    return int(fps)


def _preset(value: Any) -> str:
    if str(value) not in PRESETS:
        raise UriError(f"RealSense option preset={value!r}: one of {', '.join(PRESETS)}")
    return str(value)


def list_devices(timeout: float = 10.0) -> list[dict[str, Any]]:
    """The connected RealSense cameras: dicts with ``name``, ``serial``, ``firmware``, ``usb``
    and ``product_line`` where the camera reports them.  Empty when none is plugged in."""
    spec = {"module": __name__, "library": "librealsense", "kind": "list"}
    return list(ask_reader(spec, timeout, "listing RealSense cameras"))
