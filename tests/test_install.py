"""An installed copy (a wheel built from this checkout, installed into a folder of its own)
works without the checkout: `robot-change demo` finds its recordings (package data)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from conftest import REPO


def test_the_demo_runs_from_an_installed_copy(tmp_path: Path) -> None:
    target = tmp_path / "site"
    built = subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps",
                            "--disable-pip-version-check", "--target",
                            str(target), str(REPO)], capture_output=True, text=True, timeout=300)
    assert built.returncode == 0, built.stderr
    assert (target / "sim_fixtures" / "scenes" / "office_box_added" / "reference.oni").is_file()
    assert not (target / "sim_fixtures" / "scenes" / "office_no_change").exists()  # only these
    env = dict(os.environ, PYTHONPATH=str(target), NUMBA_CACHE_DIR=str(tmp_path / "numba"))
    work = tmp_path / "elsewhere"
    work.mkdir()
    where = subprocess.run([sys.executable, "-c", "import robot_change, sim_fixtures; "
                            "print(robot_change.__file__); print(sim_fixtures.__file__)"],
                           cwd=work, env=env, capture_output=True, text=True, timeout=60)
    assert where.returncode == 0, where.stderr
    assert all(line.startswith(str(target)) for line in where.stdout.split()), where.stdout
    demo = subprocess.run([sys.executable, "-m", "robot_change.cli", "demo", "--out",
                           str(tmp_path / "out")], cwd=work, env=env, capture_output=True,
                          text=True, timeout=600)
    assert demo.returncode == 0, demo.stdout[-3000:] + demo.stderr[-3000:]
    assert "PAUSE cause=CHANGE_CHECK" in demo.stdout
    assert (tmp_path / "out" / "report.png").read_bytes().startswith(b"\x89PNG")
