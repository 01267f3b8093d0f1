"""Checksummed, versioned .npz files: the one file format helper (scenes, mixtures, checks).

A file holds named arrays and a ``header`` array: one JSON object with the format name, its
version, the arrays' dtypes and shapes, whatever its owner adds, and a SHA-256 over the
header (without its ``sha256``, canonical JSON) and every array (name, dtype, shape,
little-endian bytes, in name order).  :func:`write` writes it atomically (temp file, fsync,
rename); :func:`read` verifies all of it and never loads pickled data.  Any ``numpy.load``
reads the files.

    write(path, "robot_change.scene", 2, arrays, {"source": uri})
    header, arrays = read(path, "robot_change.scene", 2, names, SceneFileError,
                          redo="build and save the reference again")
"""

from __future__ import annotations

import hashlib
import io
import json
from pathlib import Path
from typing import Any, Callable, Iterable

import numpy as np

import robot_change
from hw.atomic import write_atomically

__all__ = ["checksum", "read", "write"]


def checksum(header: dict[str, Any], arrays: dict[str, np.ndarray]) -> str:
    """SHA-256 (hex) over ``header`` without its ``sha256`` (canonical JSON) and every array
    (name, dtype, shape, bytes) in name order."""
    h = hashlib.sha256()
    body = {k: v for k, v in header.items() if k != "sha256"}
    h.update(json.dumps(body, sort_keys=True).encode())
    for name in sorted(arrays):
        a = arrays[name]
        h.update(f"\n{name} {a.dtype.str} {a.shape}\n".encode())
        h.update(np.ascontiguousarray(a).tobytes())
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
         ) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """Read a file :func:`write` wrote as format ``fmt``, at most version ``version``, that
    must hold the arrays ``names``; returns (header, every array of the file: the checksum
    covers them all).  ``verify(header, arrays)`` replaces the checksum test (for files of an
    older version with another checksum).

    Raises ``error`` (a message naming the file, what is wrong and ``redo``: what to do) for
    a file that is unreadable, truncated, not an .npz, of another format, newer, missing
    arrays or changed after it was written; ``FileNotFoundError`` when it does not exist.
    """
    path = Path(path)
    names = tuple(names)
    try:
        with open(path, "rb") as probe:
            magic = probe.read(4)
        if magic.startswith(b"\x93NUM"):
            raise error(f"{path}: a single .npy array, not a {fmt} file (.npz); is this the "
                        f"right file?")
        if magic != b"PK\x03\x04":  # every .npz is a zip archive
            raise error(f"{path}: not a {fmt} file (not an .npz archive: it starts with "
                        f"{magic!r}); is this the right file?")
        with np.load(path, allow_pickle=False) as data:
            present = set(data.files)
            if "header" not in present:
                raise error(f"{path}: no header, not a {fmt} file (arrays: "
                            f"{sorted(present)}); is this the right file?")
            header = json.loads(str(data["header"][()]))
            if not isinstance(header, dict):
                raise error(f"{path}: the header is not a JSON object; {redo}")
            _check_format(path, header, fmt, version, error, redo)
            missing = sorted(set(names) - present)
            if missing:
                raise error(f"{path}: arrays {missing} are missing; {redo}")
            arrays = {k: np.array(data[k]) for k in sorted(present - {"header"})}
    except FileNotFoundError:
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
