"""Shared test fixtures: where the repository and the shared real data are; a strict JSON reader."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SIM_FIXTURES = REPO / "sim_fixtures"
#: Real depth data kept beside the repository (../shared/data), never copied into it.
SHARED_DATA = REPO.parent / "shared" / "data"


def pytest_sessionstart(session: pytest.Session) -> None:
    """The numba kernels compiled (or loaded) once before any test, as setup.sh leaves them:
    the cache cleared first when the sources changed since it was filled (kernel_cache), so
    that no test runs a stale kernel and no daemon under test waits on a cold compile."""
    from robot_change.service.warmup import warm_up

    warm_up()


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """Path of ../shared/data; skips the test where it is absent (a user's clone)."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real depth data not found at {SHARED_DATA} (only present beside the "
                    "project's own checkout, not in a user's clone)")
    return SHARED_DATA


@pytest.fixture(scope="module")
def depth_frames() -> list:
    """The three (480, 640) uint16 mm frames of the fixture office_box_added's reference."""
    from hw.oni import read_oni_frames
    path = SIM_FIXTURES / "scenes" / "office_box_added" / "reference.oni"
    return [frame.depth for frame in read_oni_frames(path)]


@pytest.fixture
def small_tmpfs(tmp_path):
    """``mount(size)``: a real tmpfs of ``size`` ("64k", "2m") under tmp_path, unmounted at the
    end: a disk that really fills up (needs root: the test is skipped where it cannot mount)."""
    mounted: list[Path] = []

    def mount(size: str) -> Path:
        folder = tmp_path / f"tmpfs{len(mounted)}"
        folder.mkdir()
        done = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs",
                               str(folder)], capture_output=True, check=False)
        if done.returncode != 0:
            pytest.skip(f"cannot mount a small tmpfs here: {done.stderr.decode().strip()}")
        mounted.append(folder)
        return folder

    yield mount
    for folder in mounted:
        subprocess.run(["umount", str(folder)], capture_output=True, check=False)


def strict_loads(text: str):
    """json.loads that refuses NaN and the infinities, as JavaScript's JSON.parse does."""
    def refuse(name: str):
        raise ValueError(f"not JSON: {name}")
    return json.loads(text, parse_constant=refuse)
