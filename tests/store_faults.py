"""Kills and full disks in the middle of reference saves (issue 44), for tests/test_store.py
and bench/bench_store_faults.py: a real writer process killed with SIGKILL at random moments
and at each step of a save, and saves onto a real tmpfs that fills up.

The writer alternates two references told apart by ``source`` ("A", "B"): after any kill,
once the store has recovered (as the service does at start), the current and the previous
reference must be one of each, whole: a previous reference that became a copy of the current
one is a previous reference lost.
"""

from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

from robot_change.change.scene import SceneModel
from robot_change.service import store as store_module
from robot_change.service.store import ReferenceStore

REPO = Path(__file__).resolve().parents[1]

WRITER = """
import sys
from robot_change.change.scene import SceneModel
from robot_change.service.store import ReferenceStore
root, first, second = sys.argv[1:]
scenes = {s.source: s for s in (SceneModel.load(first), SceneModel.load(second))}
store = ReferenceStore(root, min_free_mb=0)
print("ready", flush=True)
while True:
    other = "B" if store.load("dock").source == "A" else "A"
    store.save("dock", scenes[other])
"""

#: The moments a kill aims at: any (a random time), the new file's temp file being written,
#: the new file whole before it replaces the current one, the previous reference's link.
MOMENTS = ("random", "writing the new file", "new file whole", "linking the previous")


def _moment_reached(root: Path, moment: str) -> bool:
    names = [p.name for p in root.iterdir()]
    if moment == "writing the new file":
        return any(n.startswith(".dock.next.scene.npz.") for n in names)
    if moment == "new file whole":
        return "dock.next.scene.npz" in names
    return any(n.endswith(".link.tmp") for n in names)


def state(root: Path, ignore: tuple[str, ...] = ()) -> tuple[str, str]:
    """(current, previous) sources after the recovery the service does at start; raises
    AssertionError when a file is missing, damaged or a temp file is left (files named in
    ``ignore`` aside)."""
    store = ReferenceStore(root)
    store.recover()
    left = sorted(p.name for p in root.iterdir() if p.name not in ignore)
    assert left == ["dock.prev.scene.npz", "dock.scene.npz"], left
    return store.load("dock").source, store.load_previous("dock").source


def kill_saves(tmp: Path, a: SceneModel, b: SceneModel, kills: int, seed: int = 7) -> dict:
    """``kills`` SIGKILLs of a writer saving station dock over and over, cycling through
    :data:`MOMENTS`; after each, the store's state is checked (:func:`state`).  Returns
    {"kills", "hits": moment -> kills that landed in it, "previous_lost": kills after which
    current and previous were the same reference}."""
    a.save(tmp / "a.npz")
    b.save(tmp / "b.npz")
    root = tmp / "refs"
    store = ReferenceStore(root)
    store.save("dock", a)
    store.save("dock", b)
    script = tmp / "writer.py"
    script.write_text(WRITER)
    rng = random.Random(seed)
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    hits = dict.fromkeys(MOMENTS, 0)
    lost = 0
    for trial in range(kills):
        moment = MOMENTS[trial % len(MOMENTS)]
        child = subprocess.Popen([sys.executable, str(script), str(root), str(tmp / "a.npz"),
                                  str(tmp / "b.npz")], stdout=subprocess.PIPE, env=env)
        try:
            assert child.stdout.readline() == b"ready\n"
            if moment == "random":
                time.sleep(rng.uniform(0.0, 0.7))
                hits[moment] += 1
            else:
                deadline = time.monotonic() + 10
                while time.monotonic() < deadline and not _moment_reached(root, moment):
                    pass
                hits[moment] += _moment_reached(root, moment)
            child.send_signal(signal.SIGKILL)
        finally:
            child.kill()
            child.wait(timeout=30)
            child.stdout.close()
        assert child.returncode == -signal.SIGKILL
        current, previous = state(root)
        lost += current == previous
    return {"kills": kills, "hits": hits, "previous_lost": lost}


def full_disk_saves(folder: Path, a: SceneModel, b: SceneModel, trials: int) -> dict:
    """``folder`` on a small file system holding current B and previous A with less free
    space than a reference needs: ``trials`` saves of A, each must fail with a StoreError and
    leave both references and no temp file.  The store's own free-space check is set aside
    (``_RESERVE_MB`` = 0, ``min_free_mb`` = 0): it stands for a disk filled by someone else
    between that check and the write.  Returns {"trials", "failed", "previous_lost"}."""
    from robot_change.errors import StoreError

    reserve, store_module._RESERVE_MB = store_module._RESERVE_MB, 0
    try:
        store = ReferenceStore(folder, min_free_mb=0)
        store.save("dock", a)
        store.save("dock", b)
        size = store.path("dock").stat().st_size
        with open(folder / "filler", "wb") as filler:  # leave half a reference free
            free = os.statvfs(folder).f_bavail * os.statvfs(folder).f_frsize
            filler.write(b"x" * max(0, free - size // 2))
        failed = lost = 0
        for _ in range(trials):
            try:
                store.save("dock", a)
            except StoreError:
                failed += 1
            current, previous = state(folder, ignore=("filler",))
            lost += (current, previous) != ("B", "A")
    finally:
        store_module._RESERVE_MB = reserve
    return {"trials": trials, "failed": failed, "previous_lost": lost}
