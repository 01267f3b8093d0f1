"""The controller thread's side of the service: frames and camera transitions each turn, the
commands from the queue run one at a time -- CAPTURE_REFERENCE (a reference built from fresh
frames and saved), CHECK (fresh frames fused and compared with the reference, the answer and
the last check's files), WATCH (a StationWatch started, fed and ended) -- and a failed command
turned into its FAULT."""

from __future__ import annotations

import logging
import math
import queue
import time
from typing import Any

import numpy as np

from hw.depth import DepthFrame
from robot_change.change import detect, scene
from robot_change.change.limits import detection_limit
from robot_change.change.results import ChangeSet
from robot_change.change.results import Region as ChangeRegion
from robot_change.change.scene import SceneModel
from robot_change.cloud.fusion import fuse_depth
from robot_change.errors import (
    EmptySceneError,
    ReferenceMissing,
    SceneMismatchError,
    StoreError,
)
from robot_change.fleet.messages import utc_text
from robot_change.link.protocol import (
    Captured,
    CaptureReference,
    Check,
    FaultCode,
    ModuleState,
    PauseCause,
    Watch,
)
from robot_change.noise.profile import ProfileFileError
from robot_change.service.last_check import write_last_check
from robot_change.service.params import change_params, scene_params
from robot_change.service.views import CheckView
from robot_change.service.watch import GateOptions, StationWatch

__all__ = ["Control"]

log = logging.getLogger("robot_change.service.core")  # the service's log lines keep its name


class Control:
    """The controller thread of :class:`robot_change.service.core.Service` (a base class of
    it: the attributes it uses -- frames, store, params, the command queue, the watch, the
    lock -- are the service's)."""

    def _control_main(self) -> None:
        while not self._stop.is_set():
            self.progress.beat("control")
            self._wake.wait(0.05)
            self._wake.clear()
            self._tick()
            try:
                command = self._commands.get_nowait()
            except queue.Empty:
                command = None
            if command is not None:
                self._run_command(command)

    def _tick(self) -> None:
        """Frames, camera transitions, the watch, the heartbeat: everything but commands."""
        self._camera_transitions()
        for frame, _arrived, seq in self.frames.drain():
            self.last_frame_index = frame.index
            if self._watch is not None:
                self._watch.frame(frame, seq)
        if self._watch is not None:
            if self._cancel.is_set():  # STOP, or a new command (which ends the watch itself)
                self._cancel.clear()
                if self._commands.empty():
                    self._end_watch()
                    self._refresh_heartbeat(force=True)
            elif not self._watch.step():
                self._end_watch()
        self._refresh_heartbeat()

    def _start_watch(self, station: str, reference: SceneModel) -> None:
        self._tell_stale(station, reference)
        o = self.options
        with self._lock:
            self._watch = StationWatch(station, reference, self, self.params,
                                       change_params(self.config, self.params),
                                       GateOptions(o.gate_step, o.gate_pixels, o.gate_fraction,
                                                   o.detector_threads),
                                       self._pool, self.progress, self.counters,
                                       self.watch_log, self._wake.set)
            self.activity = ModuleState.WATCHING
        log.info("WATCH %s: a change in %d of %d checks, every %d ms", station,
                 self.params["watch_m"], self.params["watch_n"], self.params["check_interval_ms"])
        if self._camera_reported is False:  # watching blind from the start: as unsafe
            self.send_fault(FaultCode.CAMERA_LOST, f"WATCH {station}: the camera is lost "
                            f"({self.camera_error}); the watch begins when it is back")
            self._lost_pause_due = True
        self._refresh_heartbeat(force=True)

    def _end_watch(self) -> None:
        with self._lock:
            watch, self._watch = self._watch, None
            if watch is not None:
                self.activity = ModuleState.IDLE
        if watch is not None:
            watch.close()
        self.progress.forget("watch")

    def _camera_transitions(self) -> None:
        """Tell the base when the camera is lost (FAULT CAMERA_LOST) and when it is back (FAULT
        CLEARED); a watch without its camera pauses the robot once, as soon as it may (armed,
        the latch clear: at the loss, or at a later ARM or WATCH)."""
        ok = self.camera_ok
        if ok != self._camera_reported and (ok or self.camera_error):  # (still opening: no)
            if ok:
                if self._camera_reported is False:
                    self.send_fault(FaultCode.CLEARED, "camera delivering frames again")
                self._lost_pause_due = False
            else:
                where = f"WATCH {self.station}: " if self._watch is not None else ""
                self.send_fault(FaultCode.CAMERA_LOST, f"{where}{self.camera_error}; retrying")
                self._lost_pause_due = True
                if self._watch is not None:
                    self._watch.camera_lost()
            self._camera_reported = ok
            self._refresh_heartbeat(force=True)
        if self._lost_pause_due and self._watch is not None and self.armed and not self.latched:
            self._lost_pause_due = False
            self.send_pause(PauseCause.CAMERA_LOST)

    def _run_command(self, m: Any) -> None:
        self._cancel.clear()
        # a capture or check reads frames and fits: it has more time than a thread turn
        work = self.progress.begin("control", f"{m.TYPE.name} {m.station}",
                                   self.progress.bound_s + self.options.command_allowance_s)
        try:
            if self._watch is None:  # STATUS's station; during a watch, the watched one
                with self._lock:
                    self.station = m.station
            # the station's reference first: a CHECK or WATCH refused for it (none, damaged)
            # leaves a watch in progress running; one that runs ends it
            reference = self.store.load(m.station) if isinstance(m, (Check, Watch)) else None
            self._end_watch()
            with self._lock:
                self.station = m.station
            if isinstance(m, CaptureReference):
                self._capture(m.station)
            elif isinstance(m, Check):
                self._check(m.station, reference)
            elif isinstance(m, Watch):
                self._start_watch(m.station, reference)
        except ReferenceMissing as exc:
            if exc.quarantined is not None:
                log.error("station %s: corrupt reference quarantined at %s", m.station,
                          exc.quarantined)
            self.send_fault(FaultCode.REFERENCE_MISSING, str(exc))
        except SceneMismatchError as exc:
            self.send_fault(FaultCode.REFERENCE_MISSING, f"station {m.station}: the reference does "
                        f"not fit this camera ({exc}); capture it again")
        except StoreError as exc:
            self.send_fault(FaultCode.STORAGE_ERROR, str(exc))
        except _CameraLost as exc:
            self.send_fault(FaultCode.CAMERA_LOST, f"{m.TYPE.name} {m.station}: {exc}")
        except _Cancelled as exc:
            self.send_fault(FaultCode.COMMAND_REFUSED, str(exc))
        except EmptySceneError as exc:
            self.send_fault(FaultCode.CAMERA_LOST, f"{m.TYPE.name} {m.station}: the camera sees "
                        f"nothing to compare ({exc})")
        except Exception as exc:  # noqa: BLE001 -- never let a command take the service down
            log.exception("%s %s failed", m.TYPE.name, m.station)
            self.send_fault(FaultCode.INTERNAL_ERROR, f"{m.TYPE.name} {m.station}: internal error "
                        f"{type(exc).__name__}: {exc}")
        finally:
            self.progress.end(work)
            with self._lock:
                if self._watch is None:
                    self.activity = ModuleState.IDLE
            self._refresh_heartbeat(force=True)

    def _set_activity(self, activity: ModuleState) -> None:
        with self._lock:
            self.activity = activity
        self._refresh_heartbeat(force=True)

    def _fresh_frames(self, n: int, what: str) -> list[DepthFrame]:
        """``n`` frames taken after now (older queued ones are passed over), in order."""
        self.frames.drain()
        frames: list[DepthFrame] = []
        per_frame = self.config.camera.read_timeout_s
        deadline = time.monotonic() + per_frame * (n + 1) + 1.0
        while len(frames) < n:
            if self._cancel.is_set():
                raise _Cancelled(f"{what} stopped by STOP or a newer command")
            if self._stop.is_set():
                raise _Cancelled(f"{what}: the service is stopping")
            if not self.camera_ok and self.camera_error:
                raise _CameraLost(self.camera_error)
            if time.monotonic() > deadline:
                raise _CameraLost(f"{len(frames)} of {n} frames within "
                                  f"{per_frame * (n + 1) + 1.0:.1f} s")
            got = self.frames.get(0.05)
            self.progress.beat("control")
            self._camera_transitions()
            self._refresh_heartbeat()
            if got is not None:
                frames.append(got[0])
                self.last_frame_index = got[0].index
        return frames

    def _capture(self, station: str) -> None:
        self.store.path(station)  # a bad name fails before any frame is read
        self._set_activity(ModuleState.CAPTURING)
        n = self.params["fuse_frames"]
        frames = self._fresh_frames(n, f"CAPTURE_REFERENCE {station}")
        t0 = time.perf_counter()
        model = scene.build_scene(frames, scene_params(self.config, self.params),
                                  source=self.camera_uri, mount=self.config.camera.mount(),
                                  noise=self.config.camera.noise_profile(self.camera.model))
        path = self.store.save(station, model)
        limit = detection_limit(model.depth, model.noise, change_params(self.config, self.params),
                                model.params.cloud.leaf_m, model.intrinsics.fx).median_m
        smallest_mm = min(round(limit * 1000), 0xFFFF) if math.isfinite(limit) else 0
        log.info("station %s: reference of %d frames (%d points, K=%d, noise %s, smallest change "
                 "seen %d mm) built in %.0f ms, saved to %s", station, n, len(model),
                 model.mixture.n_components, model.noise.name, smallest_mm,
                 (time.perf_counter() - t0) * 1e3, path)
        if model.moved_while_captured:  # told, not refused: no still real capture to set that on
            log.warning("station %s: the view moved while the reference's %d frames were taken "
                        "(drift %.2f; still: about 1): it is blurred and its noise profile "
                        "raised (%s); capture it again with the robot still", station, n,
                        model.drift, model.noise.name)
        # version 4: what the station can see, with the answer
        self._send(Captured(station, smallest_mm, model.noise.name) if self.link.version >= 4
                   else Captured(station))

    def _tell_stale(self, station: str, reference: SceneModel) -> None:
        """Say (once for each difference) where the configuration differs from what the
        station's reference was captured with: the camera's mounting (base-frame results use
        the configuration's), its noise profile and the cloud's parameters (the reference's
        are used: the configuration's take effect at the next capture)."""
        said = []
        mount = self.config.camera.mount()
        if reference.mount is not None and reference.mount != mount:
            said.append(f"the camera mounted at {reference.mount.to_dict()}, the configuration "
                        f"says {mount.to_dict()} (base-frame results use the configuration's)")
        try:  # a check does not need the configured profile: an unreadable file fails no check
            profile = self.config.camera.noise_profile(self.camera.model).name
        except ProfileFileError as exc:
            profile = f"an unreadable file ({exc})"
        if profile != reference.noise.name:
            said.append(f"noise profile {reference.noise.name}, the configuration says "
                        f"{profile} (the reference's is used)")
        _, differ = scene.scene_differences(
            reference, (reference.intrinsics, scene_params(self.config, self.params)))
        if differ:
            said.append(f"cloud parameters {'; '.join(differ)} (the reference's are used)")
        text = "; ".join(said)
        if text and self._stale_told.get(station) != text:
            log.warning("station %s: its reference was captured with %s; capture the station "
                        "again for the configuration to take effect", station, text)
        self._stale_told[station] = text

    def _check(self, station: str, reference: SceneModel) -> None:
        self._set_activity(ModuleState.CHECKING)
        self._tell_stale(station, reference)
        n = self.params["fuse_frames"]
        frames = self._fresh_frames(n, f"CHECK {station}")
        t0 = time.perf_counter()
        stamp_ns = time.time_ns()
        stack = np.stack([f.depth for f in frames])
        depth = stack[0] if n == 1 else fuse_depth(stack, reference.params.min_valid(n))
        changes = detect.detect_changes(reference, depth, change_params(self.config, self.params),
                                        intrinsics=frames[0].intrinsics)
        regions = self._kept_regions(changes)
        ms = (time.perf_counter() - t0) * 1e3
        self.counters["checks"] += 1
        reg = changes.registration
        log.info("CHECK %s: %s in %.0f ms (%d frames fused; registration %.0f mm %.1f deg, "
                 "fitness %.2f)", station, changes.outcome if changes.outcome !=
                 "changed" or not regions else f"{len(regions)} changed region(s)", ms, n,
                 1e3 * float(np.linalg.norm(reg.translation_m)), reg.rotation_deg, reg.fitness)
        self.last_check = {"station": station, "regions": len(regions), "ms": round(ms, 1),
                           "frame_index": frames[-1].index, "outcome": changes.outcome,
                           "time": utc_text(time.time())}
        changed = changes.outcome != "not_at_station" and bool(regions)
        if changed and self.may_pause():
            # the stop first: writing the check's files (compressed, fsynced) takes tens of ms
            self.send_pause(PauseCause.CHANGE_CHECK)
        # written before the answer, so that a base (or a person) told of this check finds them
        self._write_check(station, reference, depth, changes, regions)
        if changes.outcome == "not_at_station":
            self._answer_not_at_station(station, changes, "CHECK")
        elif changed:
            self.send_report(station, changes)
        else:
            self.send_no_change(station, changes)
        # the answers are queued for the link: the view for Foxglove is drawn on its own thread
        self.views.submit(CheckView(station, reference, depth, changes, self.config.camera.mount(),
                                    stamp_ns))

    def _write_check(self, station: str, reference: SceneModel, depth: np.ndarray,
                     changes: ChangeSet, regions: list[ChangeRegion]) -> None:
        """The last check's files (robot_change.service.last_check)."""
        write_last_check(self.options.report_dir, self.config, station, reference, depth,
                         changes, regions)


class _CameraLost(Exception):
    """No frames for a capture or check."""


class _Cancelled(Exception):
    """STOP (or a newer command) ended a capture or check."""
