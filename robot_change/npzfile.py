"""Checksummed, versioned .npz files: the one file format helper (scenes, mixtures, checks).

A file holds named arrays and a ``header`` array: one JSON object with the format name, its
version, the arrays' dtypes and shapes, whatever its owner adds, and a SHA-256 over the
header (without its ``sha256``, canonical JSON) and every array (name, dtype, shape,
little-endian bytes, in name order).  :func:`write` writes it atomically (temp file, fsync,
rename); :func:`read` verifies all of it and never loads pickled data.  Before it allocates
anything, :func:`read` checks the size every member declares (a few bytes of a crafted file can
declare gigabytes) against a budget, the members against the header's own declaration, and
the owner's limits (``limits``).  Any ``numpy.load`` reads the files.

    write(path, "robot_change.scene", 2, arrays, {"source": uri})
    header, arrays = read(path, "robot_change.scene", 2, names, SceneFileError,
                          redo="build and save the reference again")
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import stat
import zipfile
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import numpy as np

import robot_change
from hw.atomic import write_atomically

__all__ = ["MAX_BYTES", "Declared", "checksum", "read", "write"]

#: Bytes the arrays of one file may declare in all (a VGA reference declares ~8 MB): checked
#: before anything is read, so a crafted file cannot make a reader allocate more.
MAX_BYTES = 128 * 2**20
#: Bytes the JSON header may declare (a reference's is a few kB).
MAX_HEADER_BYTES = 4 * 2**20

#: name -> (dtype, shape) of every array a file declares, from the members' .npy headers.
Declared = dict[str, tuple[np.dtype, tuple[int, ...]]]


def checksum(header: dict[str, Any], arrays: dict[str, np.ndarray]) -> str:
    """SHA-256 (hex) over ``header`` without its ``sha256`` (canonical JSON) and every array
    (name, dtype, shape, bytes) in name order."""
    h = hashlib.sha256()
    body = {k: v for k, v in header.items() if k != "sha256"}
    h.update(json.dumps(body, sort_keys=True).encode())
    for name in sorted(arrays):
        a = arrays[name]
        h.update(f"\n{name} {a.dtype.str} {a.shape}\n".encode())
        h.update(np.ascontiguousarray(a).reshape(-1).view(np.uint8))  # no copy
    return h.hexdigest()


def write(path: str | Path, fmt: str, version: int, arrays: dict[str, np.ndarray],
          header: dict[str, Any] | None = None, *, compress: bool = True) -> dict[str, Any]:
    """Write ``arrays`` and a header (``header``'s fields plus ``format``, ``version``,
    ``saved_by``, ``arrays``: dtypes and shapes, ``sha256``) to ``path`` atomically.  Returns
    the header written."""
    arrays = {k: np.asarray(v) for k, v in arrays.items()}
    full = dict(header or {})
    full.update({"format": fmt, "version": int(version),
                 "saved_by": robot_change.__version__,
                 "arrays": {k: [a.dtype.str, list(a.shape)] for k, a in arrays.items()}})
    full["sha256"] = checksum(full, arrays)
    buf = io.BytesIO()
    save = np.savez_compressed if compress else np.savez
    save(buf, header=np.array(json.dumps(full, sort_keys=True)), **arrays)
    write_atomically(Path(path), buf.getvalue())
    return full


def read(path: str | Path, fmt: str, version: int, names: Iterable[str],
         error: type[Exception], redo: str, *,
         verify: Callable[[dict[str, Any], dict[str, np.ndarray]], bool] | None = None,
         limits: Callable[[dict[str, Any], Declared], None] | None = None,
         max_bytes: int = MAX_BYTES,
         ) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """Read a file :func:`write` wrote as format ``fmt``, at most version ``version``, that
    must hold the arrays ``names``; returns (header, every array of the file: the checksum
    covers them all).  ``verify(header, arrays)`` replaces the checksum test (for files of an
    older version with another checksum).  ``limits(header, declared)`` raises ``error`` (its
    message without the path) for declared shapes its owner cannot take; it runs after the
    header is read and before any array is.  ``max_bytes``: the arrays' declared bytes in all.

    Raises ``error`` (a message naming the file, what is wrong and ``redo``: what to do) for
    a file that is unreadable, truncated, not an .npz, not a regular file (a FIFO would block
    the reader), of another format, newer, missing arrays, larger than its budget, not what
    its header declares or changed after it was written; ``FileNotFoundError`` when it does not
    exist, ``PermissionError`` when this user may not read it (the file may be sound).
    """
    path = Path(path)
    names = tuple(names)
    try:
        if not stat.S_ISREG(os.stat(path).st_mode):
            raise error(f"{path}: not a regular file (a folder, a FIFO or a device); is this "
                        "the right file?")
        with open(path, "rb") as probe:
            magic = probe.read(4)
        if magic.startswith(b"\x93NUM"):
            raise error(f"{path}: a single .npy array, not a {fmt} file (.npz); is this the "
                        f"right file?")
        if magic != b"PK\x03\x04":  # every .npz is a zip archive
            raise error(f"{path}: not a {fmt} file (not an .npz archive: it starts with "
                        f"{magic!r}); is this the right file?")
        declared = _declared(path, fmt, error, redo)
        _check_budget(path, declared, max_bytes, error, redo)
        with np.load(path, allow_pickle=False) as data:
            header = json.loads(str(data["header"][()]))
            if not isinstance(header, dict):
                raise error(f"{path}: the header is not a JSON object; {redo}")
            _check_format(path, header, fmt, version, error, redo)
            missing = sorted(set(names) - set(declared))
            if missing:
                raise error(f"{path}: arrays {missing} are missing; {redo}")
            arrays_only = {k: v for k, v in declared.items() if k != "header"}
            _check_declaration(path, header, arrays_only, error, redo)
            if limits is not None:
                try:
                    limits(header, arrays_only)
                except error as exc:
                    raise error(f"{path}: {exc}; {redo}") from None
            arrays = {k: np.array(data[k]) for k in sorted(arrays_only)}
    except (FileNotFoundError, PermissionError):
        raise
    except error:
        raise
    except Exception as exc:  # BadZipFile, zlib.error, EOFError, ValueError, KeyError, ...
        raise error(f"{path}: not a readable {fmt} file, truncated or damaged "
                    f"({type(exc).__name__}: {exc}); {redo}") from exc
    good = verify(header, arrays) if verify is not None else \
        header.get("sha256") == checksum(header, arrays)
    if not good:
        raise error(f"{path}: checksum mismatch, the file was changed or damaged after it was "
                    f"written; {redo}")
    return header, arrays


def _declared(path: Path, fmt: str, error: type[Exception], redo: str) -> Declared:
    """Every member's dtype and shape from its .npy header (reads a few hundred bytes each)."""
    out: Declared = {}
    with zipfile.ZipFile(path) as archive:
        members = archive.infolist()
        if "header.npy" not in {m.filename for m in members}:
            raise error(f"{path}: no header, not a {fmt} file (arrays: "
                        f"{sorted(m.filename.removesuffix('.npy') for m in members)}); is this "
                        "the right file?")
        for info in members:
            name = info.filename.removesuffix(".npy")
            with archive.open(info) as member:
                major, _minor = np.lib.format.read_magic(member)
                if major == 1:
                    shape, _, dtype = np.lib.format.read_array_header_1_0(member)
                elif major == 2:
                    shape, _, dtype = np.lib.format.read_array_header_2_0(member)
                else:
                    raise error(f"{path}: member {name!r} is .npy format {major}, which this "
                                f"reader does not take; {redo}")
            if dtype.hasobject:
                raise error(f"{path}: member {name!r} holds Python objects; {redo}")
            out[name] = (dtype, tuple(int(n) for n in shape))
    return out


def _nbytes(dtype: np.dtype, shape: tuple[int, ...]) -> int:
    n = dtype.itemsize
    for d in shape:
        n *= d
    return n


def _check_budget(path: Path, declared: Declared, max_bytes: int, error: type[Exception],
                  redo: str) -> None:
    header = _nbytes(*declared["header"])
    if header > MAX_HEADER_BYTES:
        raise error(f"{path}: the header declares {header / 2**20:.0f} MiB (at most "
                    f"{MAX_HEADER_BYTES // 2**20} MiB); {redo}")
    total = sum(_nbytes(*v) for k, v in declared.items() if k != "header")
    if total > max_bytes:
        big = max((k for k in declared if k != "header"), key=lambda k: _nbytes(*declared[k]))
        dtype, shape = declared[big]
        raise error(f"{path}: the arrays declare {total / 2**20:.0f} MiB (at most "
                    f"{max_bytes // 2**20} MiB; {big!r} alone is {dtype.str} {shape}); {redo}")


def _check_declaration(path: Path, header: dict[str, Any], declared: Declared,
                       error: type[Exception], redo: str) -> None:
    """The members are the arrays the header lists, with its dtypes and shapes (files of
    formats older than the ``arrays`` field have none to compare)."""
    listed = header.get("arrays")
    if listed is None:
        return
    if not isinstance(listed, dict) or set(listed) != set(declared):
        raise error(f"{path}: the header lists arrays {sorted(listed or ())}, the file holds "
                    f"{sorted(declared)}; {redo}")
    for name, (dtype, shape) in declared.items():
        if listed[name] != [dtype.str, list(shape)]:
            raise error(f"{path}: array {name!r} is {dtype.str} {shape}, its header says "
                        f"{listed[name]}; {redo}")


def _check_format(path: Path, header: dict[str, Any], fmt: str, version: int,
                  error: type[Exception], redo: str) -> None:
    if header.get("format") != fmt:
        raise error(f"{path}: format {header.get('format')!r} is not {fmt!r}; is this the "
                    f"right file?")
    got = header.get("version")
    if not isinstance(got, int) or isinstance(got, bool) or got < 1:
        raise error(f"{path}: bad format version {got!r}; {redo}")
    if got > version:
        made = header.get("library_version") or header.get("saved_by") or "?"
        raise error(f"{path}: {fmt} format version {got}, made by robot_change {made}; this "
                    f"robot_change {robot_change.__version__} reads up to version {version}: "
                    f"upgrade robot_change (or make the file again with this version)")
