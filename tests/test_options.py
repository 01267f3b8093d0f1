"""hw.options: the URI options every backend reads the same way, and pacing at a rate."""

import time

import pytest

from hw.errors import FrameTimeout, UriError
from hw.options import Pacer, flag, positive


@pytest.mark.parametrize("value, expected", [
    (True, True), (0, False), (1, True), ("1", True), ("YES", True), ("on", True), ("", True),
    ("0", False), ("false", False), (" Off ", False)])
def test_flags(value, expected):
    assert flag("images", "loop", value) is expected


@pytest.mark.parametrize("value", ["maybe", 2, None, 0.5])
def test_bad_flags_are_uri_errors(value):
    with pytest.raises(UriError, match="images option loop="):
        flag("images", "loop", value)


def test_positive_numbers():
    assert positive("OpenNI2", "rate", "30", "fps") == 30.0
    for bad in ("0", "-3", "nan", "inf", "x", True, None):
        with pytest.raises(UriError, match=r"OpenNI2 option rate=.*> 0 \(fps\)"):
            positive("OpenNI2", "rate", bad, "fps")


def test_pacing_at_a_rate_and_a_timeout_when_the_next_frame_is_far():
    pacer = Pacer(50.0)
    start = time.monotonic()
    for _ in range(5):
        pacer.wait(1.0, "test")
    assert time.monotonic() - start >= 0.07  # 4 periods of 20 ms after the first frame
    slow = Pacer(2.0)
    slow.wait(None, "slow")
    with pytest.raises(FrameTimeout, match="slow: no frame within 0.01 s; .* 2 fps"):
        slow.wait(0.01, "slow")
    slow.reset()
    t0 = time.monotonic()
    slow.wait(0.01, "slow")  # due at once after a reset
    assert time.monotonic() - t0 < 0.05
    Pacer(None).wait(0.0, "unpaced")  # never waits
