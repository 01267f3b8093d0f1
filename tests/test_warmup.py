"""The warm-up's split of a cold compile (robot_change.service.warmup): the helper process's
kernels are the ones a real capture-and-check path then loads, and the helper never outlives
the process that started it.  Real subprocesses, a real (empty) numba cache folder."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

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
#: the helper's share, as ``python -m robot_change.service.warmup --helper`` runs it
_HELPER_COMPILES = _LISTENER + """
helper = Listener()
with event.install_listener("numba:compile", helper):
    warmup._helper_share()
print(json.dumps(sorted(helper.compiled)))
"""
_WHOLE_PATH_COMPILES = _LISTENER + """
own, whole = Listener(), Listener()
with event.install_listener("numba:compile", own):
    warmup._own_share(Config())
with event.install_listener("numba:compile", whole):
    warmup._whole_path(Config())
print(json.dumps([sorted(own.compiled), sorted(whole.compiled)]))
"""


def _python(code_or_args: list[str], cache: Path, timeout: float = 300.0):
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache), PYTHONPATH=str(REPO))
    return subprocess.run([sys.executable, *code_or_args], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=timeout)


def test_the_two_shares_leave_the_kernels_the_whole_path_loads(tmp_path):
    """After the helper's share has filled an empty cache (in its own process), this
    process's share compiles none of the helper's kernels, and the capture-and-check path
    then compiles no kernel at all: the shares left exactly what it needs (same argument
    types).  No kernel of any copies an array into a slice, and none is compiled for two
    argument types (a literal bool, a read-only array beside a writable one: each another
    compile of the whole kernel)."""
    cache = tmp_path / "cache"
    cache.mkdir()
    helper_run = _python(["-c", _HELPER_COMPILES], cache)
    assert helper_run.returncode == 0, helper_run.stderr
    helper = json.loads(helper_run.stdout.splitlines()[-1])
    run = _python(["-c", _WHOLE_PATH_COMPILES], cache)
    assert run.returncode == 0, run.stderr
    own, whole = json.loads(run.stdout.splitlines()[-1])

    def ours(names: list[str]) -> list[str]:
        return [name for name in names if name.startswith(("robot_change.", "hw."))]

    assert ours(own), "a cold cache must compile the cloud's and mixture's kernels here"
    assert ours(helper), "a cold cache must compile the registration's kernels in the helper"
    again = sorted(set(ours(own)) & set(ours(helper)))
    assert again == [], f"the helper's kernels compiled again here: {again}"
    assert ours(whole) == [], f"no share left these for the whole path: {ours(whole)}"
    # an array-to-slice copy in a kernel costs ~2 s of compile for its shape-error message
    slices = [name for name in helper + own + whole if "raise_with_shape_context" in name]
    assert slices == [], "a kernel copies an array into a slice"
    twice = sorted({name for names in (ours(helper), ours(own + whole)) for name in names
                    if names.count(name) > 1})
    assert twice == [], f"kernels compiled for more than one argument type: {twice}"


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
