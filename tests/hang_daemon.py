"""``robot-change`` with a hang injected: the real daemon, one function made to block.

    python tests/hang_daemon.py WHERE ARM_FILE run --config FILE

WHERE: ``detector`` / ``check`` (robot_change.change.detect.detect_changes), ``capture``
(robot_change.change.scene.build_scene), ``camera`` (the image-folder source's read) or
``warmup`` (the daemon's kernel warm-up, robot_change.service.warmup.warm_up).  Once
``ARM_FILE`` exists, the next call blocks for good (as a kernel stuck in native code would)
after creating ``ARM_FILE.entered``.  Everything else is ``robot_change.cli.main``.  Used by
tests/test_daemon_faults.py and bench/bench_stall.py; never by the product.
"""

from __future__ import annotations

import os
import sys
import threading
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def _patch(where: str, arm: Path) -> None:
    import hw.images
    import robot_change.change.detect
    import robot_change.change.scene
    import robot_change.service.daemon

    owner, name = {"detector": (robot_change.change.detect, "detect_changes"),
                   "check": (robot_change.change.detect, "detect_changes"),
                   "capture": (robot_change.change.scene, "build_scene"),
                   "camera": (hw.images.ImageFolderSource, "read"),
                   "warmup": (robot_change.service.daemon, "warm_up")}[where]
    real = getattr(owner, name)
    forever = threading.Event()

    def hung(*args, **kwargs):
        if arm.exists():
            Path(f"{arm}.entered").touch()
            forever.wait()
        return real(*args, **kwargs)

    setattr(owner, name, hung)


def main() -> int:
    where, arm, *argv = sys.argv[1:]
    _patch(where, Path(arm))
    from robot_change.cli import main as cli_main

    return cli_main(argv)


if __name__ == "__main__":
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    sys.exit(main())
