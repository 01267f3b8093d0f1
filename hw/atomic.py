"""Atomic file writes: readers (and a crash, or a kill -9) see the old file or the whole new one.

The one implementation every writer in the project uses (PNG images, .oni recordings, saved
mixtures, station references): a temp file in the same folder, fsync, permissions as a plain
``open()`` would give, :func:`os.replace`, then fsync of the folder so the rename survives a
power cut.  What a killed writer leaves (a temp file named ``.<name>.<random>.tmp``, or a
staged folder named alike) is removed by :func:`remove_temp_files`, which every writer's
start-up calls for the folders it writes.
"""

from __future__ import annotations

import errno
import os
import shutil
import tempfile
import time
from pathlib import Path
from typing import BinaryIO

#: A temp file untouched this long is a dead writer's: a live one writes its temp file within
#: seconds (:func:`remove_temp_files` spares younger ones when asked to).
STALE_AFTER_S = 60.0


def remove_temp_files(folder: str | os.PathLike, target: str | None = None,
                      older_than_s: float = 0.0) -> list[Path]:
    """Remove what interrupted writes left in ``folder`` (temp files, staged folders): all of
    them, or only those of the file named ``target``; ``older_than_s`` > 0 spares those
    modified more recently (a writer still at work).  Returns what was removed; a folder that
    does not exist holds none.  Raises ``OSError`` when one cannot be removed."""
    prefix = "." if target is None else f".{target}."
    try:
        entries = list(os.scandir(folder))
    except (FileNotFoundError, NotADirectoryError):
        return []
    now = time.time()
    removed = []
    for entry in entries:
        if not (entry.name.startswith(prefix) and entry.name.endswith(".tmp")):
            continue
        try:
            if older_than_s > 0 and now - entry.stat(follow_symlinks=False).st_mtime < older_than_s:
                continue
            if entry.is_dir(follow_symlinks=False):
                shutil.rmtree(entry.path)
            else:
                os.unlink(entry.path)
        except FileNotFoundError:
            continue
        removed.append(Path(entry.path))
    return removed


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


class AtomicFile:
    """A temp file that becomes ``path`` on :meth:`commit`, or vanishes on :meth:`discard`.

    ``file`` is open for reading and writing (``w+b``), so a writer may seek back and patch a
    header before committing.  Raises ``OSError`` when the folder cannot be written.
    """

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        folder = self.path.parent
        if str(folder) and not folder.is_dir():  # name the folder, not the temp file
            if folder.exists():
                raise NotADirectoryError(errno.ENOTDIR, f"cannot write it: {folder} is not a "
                                         "folder", str(self.path))
            raise FileNotFoundError(errno.ENOENT, f"cannot write it: the folder {folder} does "
                                    "not exist", str(self.path))
        if self.path.is_dir():  # the rename would fail after the writing, naming the temp file
            raise IsADirectoryError(errno.EISDIR, "is a folder: give a file's name in it",
                                    str(self.path))
        fd, temp = tempfile.mkstemp(prefix=f".{self.path.name}.", suffix=".tmp",
                                    dir=folder if str(folder) else ".")
        self.temp_path = Path(temp)
        self.file: BinaryIO = os.fdopen(fd, "w+b")
        self._done = False

    def commit(self) -> None:
        """Flush, fsync and rename into place; then fsync the folder."""
        if self._done:
            return
        try:
            self.file.flush()
            os.fsync(self.file.fileno())
            os.fchmod(self.file.fileno(), 0o666 & ~_umask())
            self.file.close()
            os.replace(self.temp_path, self.path)
        except BaseException:
            self.discard()
            raise
        self._done = True
        _fsync_folder(self.path.parent)

    def discard(self) -> None:
        """Close and remove the temp file; ``path`` is left as it was.  The temp file goes even
        when closing fails (a full disk refusing the last buffered bytes: they are thrown away
        with it)."""
        if self._done:
            return
        self._done = True
        try:
            self.file.close()
        except OSError:
            pass
        finally:
            try:
                self.temp_path.unlink()
            except FileNotFoundError:
                pass

    def __enter__(self) -> BinaryIO:
        return self.file

    def __exit__(self, exc_type, exc, traceback) -> None:
        if exc_type is None:
            self.commit()
        else:
            self.discard()


def write_atomically(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically (see the module docstring)."""
    with AtomicFile(path) as handle:
        handle.write(data)


def commit_folder(staged: str | os.PathLike, path: str | os.PathLike) -> None:
    """Move a folder written in full under a temporary name into place at ``path`` (which must
    not exist): its files are fsynced, it is renamed (atomic on one file system), and the parent
    folder is fsynced.  Readers see no folder or the whole one.  Raises ``OSError``."""
    staged, path = Path(staged), Path(path)
    for item in staged.iterdir():
        if item.is_file():
            fd = os.open(item, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
    _fsync_folder(staged)
    if path.exists():  # os.rename would replace an empty folder without a word
        raise FileExistsError(errno.EEXIST, "exists already", str(path))
    os.rename(staged, path)
    _fsync_folder(path.parent)


def _fsync_folder(folder: Path) -> None:
    try:
        fd = os.open(folder if str(folder) else ".", os.O_RDONLY)
    except OSError:
        return  # no directory fds here: the rename is done, its durability is best effort
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)
