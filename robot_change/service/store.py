"""Per-station references on disk: one verified scene file per station, the previous kept.

    root/
      dock.scene.npz                 the reference of station "dock" (SceneModel.save)
      dock.prev.scene.npz            the one it replaced
      dock.next.scene.npz            only while a save is under way (or was killed in it)
      quarantine/
        dock.scene.npz.20250101T120000.123456Z          a file that failed verification
        dock.scene.npz.20250101T120000.123456Z.txt      why

Every write is atomic (hw.atomic: temp file, fsync, rename).  A save writes the new reference
whole first (``dock.next.scene.npz``), then keeps the current one as the previous (a hard link:
no copy, nothing written) and renames the new one into place: a save that fails (a full disk)
or is killed before that last rename changes nothing, and :meth:`ReferenceStore.recover`, at
start, completes one killed between the two renames.  Every load is verified
(``SceneModel.load``: format, version, checksum).  A file that fails is never used and never
deleted: it is moved to ``quarantine/`` and reported (:class:`ReferenceMissing` names it).  The
previous version is only ever used when asked for (:meth:`ReferenceStore.load_previous`).
Station names come from the serial line: they are checked to be names, never paths.
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime
import logging
import os
import shutil
from pathlib import Path
from typing import Any

from hw.atomic import AtomicFile, remove_temp_files, write_atomically
from robot_change import validate
from robot_change.change.scene import SceneModel
from robot_change.errors import (
    ReferenceMissing,
    SceneFileError,
    StationNameError,
    StoreError,
)

__all__ = ["ReferenceStore", "StationInfo", "check_station", "CURRENT", "PREVIOUS"]

log = logging.getLogger(__name__)

#: File name endings of the current and the previous reference.
CURRENT = ".scene.npz"
PREVIOUS = ".prev.scene.npz"
#: A new reference, written whole before it replaces the current one.
NEXT = ".next.scene.npz"
QUARANTINE = "quarantine"
MAX_STATION = validate.MAX_STATION
#: Stations a store holds at most unless configured ([store] max_stations), and the ceiling.
DEFAULT_MAX_STATIONS = 64
MAX_STATIONS_LIMIT = 10_000
#: Megabytes a save leaves free on the store's file system at least ([store] min_free_mb).
DEFAULT_MIN_FREE_MB = 100
#: What one reference (and its previous version) may take, for the free-space check (a VGA
#: reference is ~0.4 MB).
_RESERVE_MB = 4


def check_station(station: Any) -> str:
    """``station`` if it is a valid station name (the protocol's rule,
    :data:`robot_change.validate.STATION_RULE`: no '.', so "a.prev" cannot name the previous
    reference of station "a", and no path can be formed), else :class:`StationNameError`."""
    if not validate.is_station(station):
        raise StationNameError(f"station {station!r}: {validate.STATION_RULE}")
    return station


@dataclasses.dataclass(frozen=True)
class FileInfo:
    """A file on disk: where, how big, last written (UTC)."""

    path: Path
    size: int
    modified: datetime.datetime


@dataclasses.dataclass(frozen=True)
class StationInfo:
    """What the store holds for one station (from the file system; nothing is verified)."""

    station: str
    current: FileInfo | None
    previous: FileInfo | None
    quarantined: tuple[Path, ...]


def _file_info(path: Path) -> FileInfo | None:
    try:
        st = path.stat()
    except FileNotFoundError:
        return None
    modified = datetime.datetime.fromtimestamp(st.st_mtime, datetime.UTC)
    return FileInfo(path, st.st_size, modified)


def _fsync_dir(folder: Path) -> None:
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _default_scene_type() -> type:
    return SceneModel


class ReferenceStore:
    """The station references under ``root`` (created on the first save).

    ``scene_type`` is the class whose ``save(path)`` / ``load(path)`` (raising
    :class:`SceneFileError`) read and write one reference:
    :class:`robot_change.change.scene.SceneModel` unless given.  ``max_stations``: a new
    station beyond this many is refused (names come from the serial line: noise or a confused
    base must not fill the disk); ``min_free_mb``: a save is refused when less than this much
    would be left free on the store's file system.
    """

    def __init__(self, root: str | os.PathLike, scene_type: type | None = None, *,
                 max_stations: int = DEFAULT_MAX_STATIONS,
                 min_free_mb: int = DEFAULT_MIN_FREE_MB) -> None:
        self.root = Path(root)
        self.scene_type = scene_type if scene_type is not None else _default_scene_type()
        self.max_stations = validate.whole("ReferenceStore", "max_stations", max_stations, 1,
                                           MAX_STATIONS_LIMIT)
        self.min_free_mb = validate.whole("ReferenceStore", "min_free_mb", min_free_mb, 0,
                                          10**7)

    def __repr__(self) -> str:
        return f"ReferenceStore({str(self.root)!r})"

    # ----------------------------------------------------------------------- paths

    def path(self, station: str) -> Path:
        """The file of ``station``'s reference."""
        return self.root / (check_station(station) + CURRENT)

    def previous_path(self, station: str) -> Path:
        """The file of the reference it replaced."""
        return self.root / (check_station(station) + PREVIOUS)

    def next_path(self, station: str) -> Path:
        """Where a save writes the new reference before it replaces the current one."""
        return self.root / (check_station(station) + NEXT)

    @property
    def quarantine_dir(self) -> Path:
        return self.root / QUARANTINE

    # ----------------------------------------------------------------------- writing

    def save(self, station: str, scene: Any) -> Path:
        """Store ``scene`` as ``station``'s reference; the one it replaces becomes the previous.

        The new file is written whole first; then the current file is verified and kept as the
        previous one (a damaged one is quarantined instead, and the old previous stays); then
        the new file takes its place.  A save that fails or is killed before that last step
        leaves the current and the previous references as they were.  Raises
        :class:`StoreError` when the folder cannot be written (full disk, permissions).
        """
        current, incoming = self.path(station), self.next_path(station)
        try:
            self._check_room(station, current)
            self.root.mkdir(parents=True, exist_ok=True)
            scene.save(incoming)
            if current.exists():
                try:
                    self.scene_type.load(current)
                except SceneFileError as exc:
                    self._quarantine(current, exc)
                else:
                    self._keep_as_previous(current, self.previous_path(station))
            os.replace(incoming, current)
            _fsync_dir(self.root)
        except StoreError:  # the damaged current reference cannot be quarantined
            with contextlib.suppress(OSError):
                incoming.unlink(missing_ok=True)
            raise
        except OSError as exc:
            with contextlib.suppress(OSError):  # a folder that cannot be written holds none
                incoming.unlink(missing_ok=True)
            raise StoreError(
                f"station {station!r}: cannot write its reference in {self.root} "
                f"({exc.strerror or exc}); check free space and that the service user owns "
                "the folder") from exc
        log.info("station %s: reference saved to %s", station, current)
        return current

    @staticmethod
    def _keep_as_previous(current: Path, previous: Path) -> None:
        """Make ``previous`` the file ``current`` is, atomically: a hard link renamed into
        place (nothing is written: a full disk cannot stop it); a copy where the file system
        has no hard links."""
        link = previous.with_name(f".{previous.name}.{os.getpid()}.link.tmp")
        link.unlink(missing_ok=True)
        try:
            os.link(current, link)
        except OSError:
            with AtomicFile(previous) as out, open(current, "rb") as src:
                shutil.copyfileobj(src, out, 1 << 20)
            return
        try:
            os.replace(link, previous)
        except OSError:
            link.unlink(missing_ok=True)
            raise

    def _check_room(self, station: str, current: Path) -> None:
        """Refuse a new station beyond ``max_stations`` and a save that would leave less than
        ``min_free_mb`` free (:class:`StoreError`; its text names no path: it goes to the base)."""
        if not current.exists():
            held = len(self.stations())
            if held >= self.max_stations:
                raise StoreError(
                    f"station {station!r} refused: the store holds {held} stations, the limit "
                    f"([store] max_stations); capture an existing station again, or delete "
                    "stations or raise the limit on the module")
        folder = next((p for p in (self.root, *self.root.parents) if p.exists()), Path("."))
        try:
            free_mb = shutil.disk_usage(folder).free / 1e6
        except OSError:
            return  # the write itself will say what is wrong
        if free_mb < self.min_free_mb + _RESERVE_MB:
            raise StoreError(
                f"station {station!r} refused: {free_mb:.0f} MB free on the module's disk, "
                f"a reference needs {_RESERVE_MB} MB and {self.min_free_mb} MB are kept free "
                "([store] min_free_mb); free some space on the module")

    def delete(self, station: str) -> list[Path]:
        """Remove ``station``'s reference and its previous version; returns the files removed
        (none when there was nothing).  Quarantined files stay."""
        removed = []
        for path in (self.path(station), self.previous_path(station)):
            try:
                path.unlink()
            except FileNotFoundError:
                continue
            except OSError as exc:
                raise StoreError(f"station {station!r}: cannot remove {path} "
                                 f"({exc.strerror}); check the folder's permissions") from exc
            removed.append(path)
        if removed:
            _fsync_dir(self.root)
            log.info("station %s: reference deleted", station)
        return removed

    # ----------------------------------------------------------------------- reading

    def load(self, station: str) -> Any:
        """``station``'s reference, verified.

        Raises :class:`ReferenceMissing` when there is none, or when its file failed
        verification: the file is then moved to ``quarantine/`` and the error names it, and
        whether a previous version exists (:meth:`load_previous` loads it, on request only).
        """
        return self._load(station, self.path(station), previous=False)

    def load_previous(self, station: str) -> Any:
        """The reference ``station`` had before the last save, verified (as :meth:`load`)."""
        return self._load(station, self.previous_path(station), previous=True)

    def stations(self) -> list[str]:
        """The stations with a current reference file, sorted (files are not verified)."""
        try:
            names = [p.name[: -len(CURRENT)] for p in self.root.iterdir()
                     if p.name.endswith(CURRENT) and p.is_file()]
        except FileNotFoundError:
            return []
        return sorted(n for n in names if validate.is_station(n))

    def info(self, station: str) -> StationInfo:
        """Files held for ``station`` (current, previous, quarantined); reads no file."""
        prefix = check_station(station) + "."
        try:
            bad = sorted(p for p in self.quarantine_dir.iterdir()
                         if p.name.startswith(prefix) and not p.name.endswith(".txt"))
        except FileNotFoundError:
            bad = []
        return StationInfo(station, _file_info(self.path(station)),
                           _file_info(self.previous_path(station)), tuple(bad))

    def recover(self) -> list[Path]:
        """Put right what writes that were killed left; call once at start, before any save.

        Temp files (here and in quarantine/) are removed.  A new reference left by a killed
        save (``<station>.next.scene.npz``) takes its place when the save had already kept the
        current one as the previous (the two are then one file), else it is removed: either
        way the store holds whole references, the previous one never lost.  Returns the files
        removed or moved into place."""
        done = remove_temp_files(self.root) + remove_temp_files(self.quarantine_dir)
        try:
            incoming = [p for p in self.root.iterdir() if p.name.endswith(NEXT)]
        except FileNotFoundError:
            return done
        for path in incoming:
            station = path.name[: -len(NEXT)]
            if not validate.is_station(station):
                continue
            current, previous = self.path(station), self.previous_path(station)
            if previous.exists() and current.exists() and os.path.samefile(previous, current):
                os.replace(path, current)
                log.warning("station %s: a save killed before its end completed", station)
            else:
                path.unlink()
            done.append(path)
        if done:
            _fsync_dir(self.root)
            log.info("recovered %d file(s) left by interrupted writes in %s", len(done),
                     self.root)
        return done

    # ----------------------------------------------------------------------- internals

    def _load(self, station: str, path: Path, previous: bool) -> Any:
        which = "previous reference" if previous else "reference"
        prev = self.previous_path(station)
        try:
            return self.scene_type.load(path)
        except FileNotFoundError:
            raise ReferenceMissing(
                f"station {station!r}: no {which} stored ({path} does not exist); capture one "
                f"with CAPTURE_REFERENCE {station}" + self._previous_hint(prev, previous),
                station=station) from None
        except SceneFileError as exc:
            moved = self._quarantine(path, exc)
            raise ReferenceMissing(
                f"station {station!r}: the {which} {path.name} failed verification and was "
                f"moved to {moved} ({exc}); capture the reference again with "
                f"CAPTURE_REFERENCE {station}" + self._previous_hint(prev, previous),
                station=station, quarantined=moved) from exc
        except OSError as exc:
            raise StoreError(f"station {station!r}: cannot read {path} ({exc.strerror}); check "
                             "its and its folder's permissions: the service's user must read "
                             "them") from exc

    @staticmethod
    def _previous_hint(prev: Path, previous: bool) -> str:
        if previous or not prev.exists():
            return ""
        return f", or use the previous reference {prev.name} (load_previous)"

    def _quarantine(self, path: Path, reason: Exception) -> Path:
        """Move a file that failed verification to quarantine/ with a timestamp and a note;
        :class:`StoreError` (the file left where it is) when that folder cannot be written."""
        folder = self.quarantine_dir
        stamp = datetime.datetime.now(datetime.UTC).strftime("%Y%m%dT%H%M%S.%fZ")
        try:
            folder.mkdir(exist_ok=True)
            target = folder / f"{path.name}.{stamp}"
            n = 1
            while target.exists():
                target = folder / f"{path.name}.{stamp}-{n}"
                n += 1
            os.replace(path, target)
        except OSError as exc:
            log.error("%s failed verification (%s) and cannot be moved to %s: %s", path, reason,
                      folder, exc)
            raise StoreError(f"{path.name} failed verification and cannot be moved to "
                             f"{folder} ({exc.strerror or exc}); the service's user must be "
                             "able to write that folder") from exc
        _fsync_dir(self.root)
        try:
            write_atomically(target.with_name(target.name + ".txt"),
                             f"{path}\nquarantined {stamp}\n{reason}\n".encode())
        except OSError as exc:  # the file is in quarantine: its note is a courtesy
            log.warning("%s: cannot write its note (%s)", target, exc)
        log.error("%s failed verification (%s); moved to %s", path, reason, target)
        return target
