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
class Listener(event.Listener):
    def __init__(self):
        self.compiled = set()
    def on_start(self, ev):
        f = ev.data["dispatcher"].py_func
        self.compiled.add(f.__module__ + "." + f.__qualname__)
    def on_end(self, ev):
        pass
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
    """After the helper's share has filled an empty cache, this process's share compiles
    none of the helper's (registration's, transport's), and the capture-and-check path then
    compiles none of the helper's nor the depth decoders': the shares left exactly what it
    needs (same argument types).  No kernel of either copies an array into a slice."""
    cache = tmp_path / "cache"
    cache.mkdir()
    helper = _python(["-m", "robot_change.service.warmup", "--helper", str(os.getpid())],
                     cache)
    assert helper.returncode == 0, helper.stderr
    run = _python(["-c", _WHOLE_PATH_COMPILES], cache)
    assert run.returncode == 0, run.stderr
    own, whole = json.loads(run.stdout.splitlines()[-1])
    ours = [name for name in own if name.startswith(("robot_change.", "hw."))]
    assert ours, "a cold cache must compile the cloud's and mixture's kernels here"

    def helpers(names: list[str]) -> list[str]:  # registration's (its surface segments are
        # the regions', in this share) and transport's
        return [name for name in names if name.startswith(
            ("robot_change.change.registration.", "robot_change.change.transport"))
            and not name.startswith("robot_change.change.registration.surfaces.")]

    assert helpers(own) == [], f"the helper's kernels compiled again here: {helpers(own)}"
    assert helpers(whole) == [], f"the helper did not leave these for the whole path: " \
        f"{helpers(whole)}"
    decoders = [name for name in whole if name.startswith("hw.")]
    assert decoders == [], f"this share did not leave these for the whole path: {decoders}"
    # an array-to-slice copy in a kernel costs ~2 s of compile for its shape-error message
    slices = [name for name in own + whole if "raise_with_shape_context" in name]
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
