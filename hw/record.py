"""Any depth source recorded to a file, stopped cleanly: an OpenNI2 ``.oni`` recording, a ROS 2
bag (MCAP storage) or a RealSense recording (``.db3``, written by librealsense).

    with open_depth("openni2://") as camera:
        record(camera, "kitchen.oni")                      # until the end, --frames or Ctrl-C
        record(camera, "kitchen_bag", format="rosbag2")    # a ROS 2 bag folder
        record(camera, "kitchen.db3", format="realsense")  # librealsense's recorder

The writers are atomic (the file or folder appears only when complete) and both stop the same
way: after ``frames``, at the end of the source, or at SIGINT / SIGTERM, with what was recorded
so far kept as a finished recording.
"""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
import logging
import os
import signal
import threading
import time
from collections.abc import Callable, Iterator

from hw.depth import DepthFrame, DepthSource
from hw.errors import ArgumentError, DepthFileError, DeviceError
from hw.oni import write_oni

__all__ = ["FORMATS", "record"]

log = logging.getLogger(__name__)

#: What :func:`record` writes: ``oni`` (an OpenNI2 recording, one file), ``rosbag2`` (a ROS 2
#: bag folder with MCAP storage, as ``ros2 bag record -s mcap`` makes) and ``realsense`` (a
#: RealSense ``.db3``: :func:`hw.realsense_record.write_realsense_recording`).
FORMATS = ("oni", "rosbag2", "realsense")
#: A frame stamped before this (µs since 1970: 2001-09-09) carries a camera's clock (time since
#: it started: OpenNI2, a RealSense's hardware clock) or a frame count, not the time of day.
CLOCK_TIME_FROM_US = 10**15


def record(source: DepthSource, out_path: str | os.PathLike[str], frames: int | None = None,
           codec: str = "16zt", timeout: float = 5.0,
           progress: Callable[[int, float, int], None] | None = None, *,
           format: str = "oni") -> int:
    """Copy frames from any depth source into a recording; returns how many.

    Stops after ``frames`` (default: never), at the end of the source, or -- called from the
    main thread -- at SIGINT or SIGTERM (Ctrl-C, ``kill``, ``systemctl stop``): the frames so
    far become a finished, playable recording either way, and the signal handlers are put back
    afterwards.  ``format`` is one of :data:`FORMATS`.  ``.oni``: timestamps shifted to start
    at 0; ``codec`` ``"16zt"`` (lossless, about 4x smaller than raw on Kinect depth), ``"16z"``
    (lossless, for unquantised depth) or ``"none"``.  ``rosbag2``: ``out_path`` is the bag's
    folder (it must not exist yet), header stamps are the frames' timestamps as they are
    (:func:`hw.rosbag.write_rosbag2`) when they are times of day, else (a camera's own clock,
    a frame count: :data:`CLOCK_TIME_FROM_US`) moved to the time of day the first frame was
    recorded, as ROS tools expect; the camera's name and serial in its metadata;
    ``realsense``: ``out_path`` ends in ``.db3``, frame numbers and timestamps as they are;
    ``codec`` ``"png"`` (librealsense's compressedDepth) or ``"none"`` (raw Images).  Each
    keeps the frames' intrinsics and the camera's name.  ``progress(frames, seconds,
    bytes)`` is called after every frame.  Opens the source if needed; the caller closes it.
    The recording appears only when complete (written atomically); on an error nothing is
    left, and none is written over an existing file or folder.
    """
    if frames is not None and frames < 1:
        raise ArgumentError(f"frames={frames}: record at least one frame")
    if format not in FORMATS:
        raise ArgumentError(f"format={format!r}: choose one of {', '.join(FORMATS)}")
    if format == "oni" and os.path.lexists(out_path):  # the bag and RealSense writers refuse too
        raise DepthFileError(f"{out_path}: exists; a recording is not written over it")
    stop = threading.Event()
    with _stopped_by_signals(stop):
        source.open()
        stream = _frames_until_done(source, frames, timeout, stop)
        first = next(stream, None)
        if first is None:
            raise DepthFileError(f"{source.uri or 'the source'} delivered no frame; nothing "
                                 "recorded")
        started = time.monotonic()
        tell = None if progress is None else (
            lambda count, size: progress(count, time.monotonic() - started, size))
        everything = itertools.chain([first], stream)
        info = getattr(source, "info", None) or {}  # the camera it names, its fps
        if format == "rosbag2":
            from hw.rosbag import write_rosbag2

            return write_rosbag2(out_path, _times_of_day(everything), camera=info,
                                 on_frame=tell)
        fps = int(info.get("fps") or 30)
        if format == "realsense":
            from hw.realsense_record import write_realsense_recording

            return write_realsense_recording(out_path, everything, fps=fps, on_frame=tell,
                                             name=info.get("name"),
                                             serial=str(info.get("serial") or "000000000001"),
                                             compress=codec != "none")
        return write_oni(out_path, everything, fps=fps, codec=codec, on_frame=tell,
                         camera=str(info.get("name") or ""))


def _times_of_day(frames: Iterator[DepthFrame]) -> Iterator[DepthFrame]:
    """``frames`` with timestamps that are not times of day (:data:`CLOCK_TIME_FROM_US`) moved
    by one offset so that the first is now; others as they are."""
    offset = None
    for frame in frames:
        if offset is None:
            offset = 0 if frame.timestamp_us >= CLOCK_TIME_FROM_US else \
                time.time_ns() // 1000 - frame.timestamp_us
            if offset:
                log.info("the frames are stamped by the camera's clock (%d µs): recorded with "
                         "the time of day added", frame.timestamp_us)
        yield dataclasses.replace(frame, timestamp_us=frame.timestamp_us + offset) if offset \
            else frame


@contextlib.contextmanager
def _stopped_by_signals(stop: threading.Event) -> Iterator[None]:
    """SIGINT and SIGTERM set ``stop`` instead of ending the process, while inside (main
    thread only: elsewhere signals cannot be caught, and Ctrl-C still ends the loop)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    for sig in previous:
        signal.signal(sig, lambda _sig, _frame: stop.set())
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _frames_until_done(source: DepthSource, frames: int | None, timeout: float,
                       stop: threading.Event) -> Iterator[DepthFrame]:
    """Frames of ``source`` until it ends, ``frames`` were read, or ``stop`` (or Ctrl-C).  A
    source that fails after the first frame ends the recording, which keeps what it has."""
    count = 0
    while (frames is None or count < frames) and not stop.is_set():
        try:
            frame = source.read(timeout)
        except KeyboardInterrupt:
            return
        except (DeviceError, DepthFileError) as exc:
            if not count:
                raise
            log.warning("recording ends after %d frame(s): %s; the file keeps them", count, exc)
            return
        if frame is None:
            return
        count += 1
        yield frame
