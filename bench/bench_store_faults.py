"""Issue 44's store targets: previous references lost over kills in the save window and on a
full disk (target 0 of 100), and temp files left once the store has recovered (target 0).

    .venv/bin/python bench/bench_store_faults.py [--kills 100] [--full-disk 20] [--json]

tests/store_faults.py does the work: a real writer process saving station dock over and over
(two references, A and B, in turn), killed with SIGKILL at random moments and at each step of
a save; then saves onto a real tmpfs (mounted here: needs root) left with half a reference
free.  After each, the store recovers as the service does at start and must hold one of A and
B as current and the other as previous, and nothing else.  A benchmark, never a test.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT))

import store_faults  # noqa: E402

from hw.depth import open_depth  # noqa: E402
from robot_change.change.scene import build_scene  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--kills", type=int, default=100)
    parser.add_argument("--full-disk", type=int, default=20, help="saves onto the full tmpfs")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    with open_depth(str(ROOT / "sim_fixtures" / "frames" / "room_vga.png")) as source:
        a = build_scene([next(iter(source))], source="A")
    b = dataclasses.replace(a, source="B")
    result = {}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        result["kills"] = store_faults.kill_saves(tmp, a, b, args.kills)
        disk = tmp / "tmpfs"
        disk.mkdir()
        mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=2m", "tmpfs", str(disk)],
                                 capture_output=True, text=True, check=False)
        if mounted.returncode != 0:
            result["full_disk"] = f"not run: cannot mount a tmpfs ({mounted.stderr.strip()})"
        else:
            try:
                result["full_disk"] = store_faults.full_disk_saves(disk, a, b, args.full_disk)
            finally:
                subprocess.run(["umount", str(disk)], check=False)
    print(json.dumps(result, indent=None if args.json else 2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
