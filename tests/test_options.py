"""hw.options: the URI options every backend reads the same way, and pacing at a rate."""

import time

import pytest

from hw.depth import Intrinsics
from hw.errors import FrameTimeout, UriError
from hw.options import LapClock, Pacer, flag, intrinsics_option, positive


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


def test_a_lap_clock_shifts_each_lap_by_the_first_s_span_and_one_period():
    clock = LapClock()
    assert [clock.stamp(t) for t in (100, 200, 400)] == [100, 200, 400]
    clock.next_lap()  # span 300, period 150
    assert [clock.stamp(t) for t in (100, 200)] == [550, 650]
    assert (clock.lap, clock.lap_frames) == (1, 2)
    clock.next_lap()
    assert clock.stamp(100) == 1000
    clock.reset()
    assert clock.stamp(7) == 7 and clock.lap == 0
    one = LapClock()  # one frame a lap: a 30 fps period
    one.stamp(0)
    one.next_lap()
    assert one.stamp(0) == 33_333


def test_an_intrinsics_option_is_four_numbers_kept_as_text_or_an_intrinsics():
    assert intrinsics_option("x", None) is None and intrinsics_option("x", " ") is None
    assert intrinsics_option("x", "525,525,2000,239.5") == "525,525,2000,239.5"  # any size
    given = Intrinsics(640, 480, 525, 525, 319.5, 239.5)
    assert intrinsics_option("x", given) is given
    for bad in ("1,2", "a,b,c,d", "525,525,nan,1", "0,525,1,1", 5):
        with pytest.raises(UriError, match="x option intrinsics="):
            intrinsics_option("x", bad)
