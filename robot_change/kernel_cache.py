"""The numba kernels' on-disk cache kept true to the sources.

numba drops a cached kernel when the kernel's own file changes, not when a kernel it calls in
another file does (its documented limit): after an update that touched only the callee, the
caller would run its old machine code, silently.  So the cache is tied to a fingerprint of
every source file of the packages (SHA-256 over their paths and contents): when the
fingerprint differs from the one stamped beside the cache, every cached kernel of those
packages is removed before any is loaded, and compiled afresh.

    clear_stale_kernels()          # before the first kernel runs (robot_change's import)

A warm-up that loaded every kernel marks the cache warm (:func:`mark_kernels_warm`) for these
sources, this numba and this Python; :func:`kernels_warm` tells the next one whether it will
only load (robot_change.service.warmup compiles a cold cache in helper processes).
"""

from __future__ import annotations

import hashlib
import logging
import os
import sys
from pathlib import Path

from hw.atomic import write_atomically

__all__ = ["clear_stale_kernels", "kernels_warm", "mark_kernels_warm", "source_fingerprint"]

log = logging.getLogger(__name__)

#: The packages whose kernels are cached: robot_change and hw.
PACKAGES = (Path(__file__).resolve().parent, Path(__file__).resolve().parents[1] / "hw")
#: numba's cache files: the index of a kernel's signatures and one object file per signature.
_CACHE_SUFFIXES = (".nbi", ".nbc")


def source_fingerprint(packages: tuple[Path, ...] = PACKAGES) -> str:
    """SHA-256 (hex) over every .py file under ``packages``: its path below its package and
    its bytes, in path order."""
    h = hashlib.sha256()
    for package in packages:
        for path in sorted(package.rglob("*.py")):
            if "__pycache__" in path.parts:
                continue
            h.update(f"{package.name}/{path.relative_to(package).as_posix()}\n".encode())
            h.update(path.read_bytes())
    return h.hexdigest()


def _cache_folder(source_dir: Path) -> Path:
    """Where numba caches the kernels of ``source_dir``'s files: under NUMBA_CACHE_DIR as
    numba lays it out (its UserProvidedCacheLocator: ``<folder name>_<SHA-1 of its absolute
    path>``), else the folder's __pycache__."""
    root = os.environ.get("NUMBA_CACHE_DIR")
    if not root:
        return source_dir / "__pycache__"
    from numba.core.caching import UserProvidedCacheLocator

    return Path(root) / UserProvidedCacheLocator.get_suitable_cache_subpath(
        str(source_dir.resolve() / "any.py"))


def _stamp_path(packages: tuple[Path, ...]) -> Path:
    root = os.environ.get("NUMBA_CACHE_DIR")
    folder = _cache_folder(packages[0]) if root else packages[0] / "__pycache__"
    return folder / "kernel-sources.sha256"


def _warm_text(packages: tuple[Path, ...]) -> str:
    """What marks the cache warm: the sources' fingerprint, numba's and Python's versions (a
    cache of another numba or Python is compiled again)."""
    import numba

    return (f"{source_fingerprint(packages)} numba {numba.__version__} "
            f"python {'.'.join(map(str, sys.version_info[:3]))}\n")


def kernels_warm(packages: tuple[Path, ...] = PACKAGES) -> bool:
    """A warm-up of these sources, this numba and this Python loaded every kernel into the
    cache (:func:`mark_kernels_warm`), and the cache was not removed since."""
    try:
        return (_stamp_path(packages).with_name("kernels-warm").read_text()
                == _warm_text(packages))
    except OSError:
        return False


def mark_kernels_warm(packages: tuple[Path, ...] = PACKAGES) -> None:
    """Mark the cache warm (after a warm-up's whole path ran); never raises: an unwritable
    cache stays unmarked."""
    try:
        marker = _stamp_path(packages).with_name("kernels-warm")
        marker.parent.mkdir(parents=True, exist_ok=True)
        write_atomically(marker, _warm_text(packages).encode())
    except OSError as exc:
        log.debug("numba cache not marked warm: %s", exc)


def clear_stale_kernels(packages: tuple[Path, ...] = PACKAGES) -> int:
    """Remove the cached kernels of ``packages`` when their sources changed since the cache
    was stamped, and stamp it; returns the number of files removed.  Never raises: a cache it
    cannot read or write is left to numba (which then compiles in memory)."""
    try:
        fingerprint = source_fingerprint(packages)
        stamp = _stamp_path(packages)
        try:
            if stamp.read_text().strip() == fingerprint:
                return 0
        except FileNotFoundError:
            pass
        removed = 0
        for package in packages:
            for source_dir in {p.parent for p in package.rglob("*.py")
                               if "__pycache__" not in p.parts}:
                folder = _cache_folder(source_dir)
                if not folder.is_dir():
                    continue
                for entry in folder.iterdir():
                    if entry.suffix in _CACHE_SUFFIXES:
                        entry.unlink(missing_ok=True)
                        removed += 1
        stamp.parent.mkdir(parents=True, exist_ok=True)
        write_atomically(stamp, (fingerprint + "\n").encode())
    except OSError as exc:
        log.debug("numba cache not checked against the sources: %s", exc)
        return 0
    if removed:
        log.info("sources changed since the kernels were cached: %d cached file(s) removed",
                 removed)
    return removed
