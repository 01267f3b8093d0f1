"""Shared test fixtures: where the repository and the shared real data are."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SIM_FIXTURES = REPO / "sim_fixtures"
#: Real depth data kept beside the repository (../shared/data), never copied into it.
SHARED_DATA = REPO.parent / "shared" / "data"


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
