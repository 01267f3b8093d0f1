"""The warm-up's split of a cold compile (robot_change.service.warmup): the helper process's
kernels are the ones a real capture-and-check path then loads, and the helper never outlives
the process that started it.  Real subprocesses, a real (empty) numba cache folder."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

from robot_change import kernel_cache
from robot_change.service import warmup

REPO = Path(__file__).resolve().parents[1]

_LISTENER = """
import json
from numba.core import event
from robot_change.service.config import Config
from robot_change.service import warmup
class Listener(event.Listener):
    def __init__(self):
        self.compiled = []  # one entry per compile: a kernel twice is two argument types
    def on_start(self, ev):
        f = ev.data["dispatcher"].py_func
        self.compiled.append(f.__module__ + "." + f.__qualname__)
    def on_end(self, ev):
        pass
"""
#: one helper's share (as ``python -m robot_change.service.warmup --share NAME PID`` runs it),
#: the kernels it compiled
_SHARE_COMPILES = _LISTENER + """
import sys
share = Listener()
with event.install_listener("numba:compile", share):
    warmup.SHARES[sys.argv[1]]()
print(json.dumps(sorted(share.compiled)))
"""
_WHOLE_PATH_COMPILES = _LISTENER + """
whole = Listener()
with event.install_listener("numba:compile", whole):
    warmup._whole_path(Config())
print(json.dumps(sorted(whole.compiled)))
"""


def _python(code_or_args: list[str], cache: Path, timeout: float = 300.0):
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache), PYTHONPATH=str(REPO))
    return subprocess.run([sys.executable, *code_or_args], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=timeout)


def _share_in(cache: Path, share: str) -> subprocess.Popen:
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache), PYTHONPATH=str(REPO))
    return subprocess.Popen([sys.executable, "-c", _SHARE_COMPILES, share], cwd=REPO, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def test_the_two_shares_leave_the_kernels_the_whole_path_loads(tmp_path):
    """Each helper's share, on an empty cache of its own (as the two run at once), compiles
    kernels the other does not (none is compiled twice); with both caches together the
    capture-and-check path compiles no kernel at all: the shares left exactly what it needs
    (same argument types).  No kernel of any copies an array into a slice, and none is
    compiled for two argument types (a literal bool, a read-only array beside a writable one:
    each another compile of the whole kernel)."""
    caches = {share: tmp_path / share for share in warmup.SHARES}
    procs = {share: _share_in(cache, share) for share, cache in caches.items()}
    compiled = {}
    for share, proc in procs.items():
        out, err = proc.communicate(timeout=300)
        assert proc.returncode == 0, err
        compiled[share] = json.loads(out.splitlines()[-1])
    both = tmp_path / "both"
    for cache in caches.values():  # numba's layout: a folder per source folder, named by its path
        shutil.copytree(cache, both, dirs_exist_ok=True)
    run = _python(["-c", _WHOLE_PATH_COMPILES], both)
    assert run.returncode == 0, run.stderr
    whole = json.loads(run.stdout.splitlines()[-1])

    def ours(names: list[str]) -> list[str]:
        return [name for name in names if name.startswith(("robot_change.", "hw."))]

    registration, cloud = ours(compiled["registration"]), ours(compiled["cloud"])
    assert cloud, "a cold cache must compile the cloud's and mixture's kernels in a helper"
    assert registration, "a cold cache must compile the registration's kernels in a helper"
    again = sorted(set(registration) & set(cloud))
    assert again == [], f"kernels both helpers compile: {again}"
    assert ours(whole) == [], f"no share left these for the whole path: {ours(whole)}"
    # an array-to-slice copy in a kernel costs ~2 s of compile for its shape-error message
    slices = [name for names in (*compiled.values(), whole) for name in names
              if "raise_with_shape_context" in name]
    assert slices == [], "a kernel copies an array into a slice"
    twice = sorted({name for names in (registration, cloud) for name in names
                    if names.count(name) > 1})
    assert twice == [], f"kernels compiled for more than one argument type: {twice}"


def test_a_warm_cache_starts_no_helper(monkeypatch):
    """The session's warm-up (conftest) marked the cache warm: warm_up only loads, no helper
    process is started (a cold cache's helpers: the test above and tests/test_daemon_faults.py's
    cold start)."""
    started = []
    monkeypatch.setattr(warmup, "_start_helper", started.append)
    assert kernel_cache.kernels_warm()
    warmup.warm_up()
    assert started == []


def test_the_helper_ends_when_its_parent_is_gone(tmp_path):
    """A daemon stopped during a cold warm-up leaves no compiling process behind."""
    cache = tmp_path / "cache"
    cache.mkdir()
    parent = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache), PYTHONPATH=str(REPO))
    helper = subprocess.Popen([sys.executable, "-c",
                               "import os, sys, time\n"
                               "from robot_change.service import warmup\n"
                               f"warmup._exit_with_parent({parent.pid})\n"
                               "time.sleep(120)\n"],
                              cwd=REPO, env=env)
    try:
        time.sleep(1.0)
        assert helper.poll() is None  # its watched process is alive: it stays
    finally:
        parent.kill()
        parent.wait()
    assert helper.wait(timeout=10) == 0
