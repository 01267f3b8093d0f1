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

_WHOLE_PATH_COMPILES = """
import json
from numba.core import event
from robot_change.service.config import Config
from robot_change.service import warmup
compiled = set()
class Listener(event.Listener):
    def on_start(self, ev):
        f = ev.data["dispatcher"].py_func
        compiled.add(f.__module__ + "." + f.__qualname__)
    def on_end(self, ev):
        pass
with event.install_listener("numba:compile", Listener()):
    warmup._whole_path(Config())
print(json.dumps(sorted(compiled)))
"""


def _python(code_or_args: list[str], cache: Path, timeout: float = 300.0):
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache), PYTHONPATH=str(REPO))
    return subprocess.run([sys.executable, *code_or_args], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=timeout)


def test_the_helpers_kernels_are_the_ones_the_whole_path_loads(tmp_path):
    """After the helper's share alone has filled an empty cache, the capture-and-check path
    compiles nothing of registration's or transport's: the helper left exactly what it
    needs (same argument types).  It compiles the cloud's, mixture's and free-space check's
    kernels itself, none of them with an array-to-slice copy."""
    cache = tmp_path / "cache"
    cache.mkdir()
    helper = _python(["-m", "robot_change.service.warmup", "--helper", str(os.getpid())],
                     cache)
    assert helper.returncode == 0, helper.stderr
    run = _python(["-c", _WHOLE_PATH_COMPILES], cache)
    assert run.returncode == 0, run.stderr
    compiled = json.loads(run.stdout.splitlines()[-1])
    ours = [name for name in compiled if name.startswith("robot_change.")]
    assert ours, "a cold cache must compile the cloud's and mixture's kernels here"
    left = [name for name in ours if name.startswith(("robot_change.change.registration.",
                                                      "robot_change.change.transport"))]
    assert left == [], f"the helper did not leave these for the whole path: {left}"
    # an array-to-slice copy in a kernel costs ~2 s of compile for its shape-error message
    slices = [name for name in compiled if "raise_with_shape_context" in name]
    assert slices == [], "a cloud, mixture or free-space kernel copies an array into a slice"


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
