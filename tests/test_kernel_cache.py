"""robot_change.kernel_cache: numba's cache keeps a kernel whose callee in another file changed
(its documented limit); the fingerprint of the sources clears it.  Shown on a real two-file
package compiled by numba in fresh processes."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from conftest import REPO

from robot_change.kernel_cache import (
    clear_stale_kernels,
    kernels_warm,
    mark_kernels_warm,
    source_fingerprint,
)

CALLER = """
from numba import njit
from kern.callee import g

@njit(cache=True)
def f(x):
    return g(x) + 1
"""
CALLEE = """
from numba import njit

@njit(cache=True)
def g(x):
    return x * {factor}
"""
RUN = """
import sys
sys.path.insert(0, sys.argv[1])
from pathlib import Path
from robot_change.kernel_cache import clear_stale_kernels
if sys.argv[2] == "clear":
    clear_stale_kernels((Path(sys.argv[1]) / "kern",))
from kern.caller import f
print(f(10))
"""


def _package(root: Path, factor: int) -> None:
    (root / "kern").mkdir(exist_ok=True)
    (root / "kern" / "__init__.py").write_text("")
    (root / "kern" / "caller.py").write_text(CALLER)
    (root / "kern" / "callee.py").write_text(CALLEE.format(factor=factor))


def _run(root: Path, mode: str, cache: Path | None) -> int:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    env.pop("NUMBA_CACHE_DIR", None)
    if cache is not None:
        env["NUMBA_CACHE_DIR"] = str(cache)
    out = subprocess.run([sys.executable, "-c", RUN, str(root), mode], env=env, check=True,
                         capture_output=True, text=True, timeout=120).stdout
    return int(out.split()[-1])


def test_numba_keeps_a_stale_caller_and_the_fingerprint_clears_it(tmp_path):
    for cache in (None, tmp_path / "numba-cache"):  # beside the sources; NUMBA_CACHE_DIR
        root = tmp_path / ("in-tree" if cache is None else "env")
        root.mkdir()
        _package(root, factor=2)
        assert _run(root, "plain", cache) == 21
        callee = root / "kern" / "callee.py"
        callee.write_text(CALLEE.format(factor=3))  # the callee alone
        # a later edit, as an update is: in the same second and at the same size Python takes
        # its old bytecode for fresh (its .pyc check), and numba compiles that
        later = callee.stat().st_mtime + 2.0
        os.utime(callee, (later, later))
        assert _run(root, "plain", cache) == 21, "numba's limit: the caller's stale code ran"
        assert _run(root, "clear", cache) == 31  # cleared, compiled again: the new callee
        assert _run(root, "clear", cache) == 31  # the stamp matches: nothing cleared now


def test_the_fingerprint_covers_every_source_file_and_only_those(tmp_path):
    _package(tmp_path, factor=2)
    package = (tmp_path / "kern",)
    before = source_fingerprint(package)
    (tmp_path / "kern" / "__pycache__").mkdir()
    (tmp_path / "kern" / "__pycache__" / "caller.f-5.py311.nbi").write_bytes(b"index")
    assert source_fingerprint(package) == before
    (tmp_path / "kern" / "callee.py").write_text(CALLEE.format(factor=2) + "\n")
    assert source_fingerprint(package) != before
    assert clear_stale_kernels(package) == 1  # the cached index, and the stamp written
    assert (tmp_path / "kern" / "__pycache__" / "kernel-sources.sha256").is_file()
    assert clear_stale_kernels(package) == 0


def test_the_warm_mark_holds_for_the_sources_it_was_made_for(tmp_path, monkeypatch):
    """A cache is warm once marked, for these sources only: a changed file makes it cold
    (a warm-up then compiles in helper processes: robot_change.service.warmup)."""
    package = tmp_path / "pkg"
    package.mkdir()
    (package / "mod.py").write_text("x = 1\n")
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "cache"))
    assert not kernels_warm((package,))
    mark_kernels_warm((package,))
    assert kernels_warm((package,))
    (package / "mod.py").write_text("x = 2\n")
    assert not kernels_warm((package,))
