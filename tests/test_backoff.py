"""hw.backoff: the one exponential back-off (camera, OpenNI2 reader, serial port)."""

import pytest

from hw.backoff import Backoff
from hw.errors import ArgumentError


def test_delays_double_to_the_cap_and_reset_starts_again():
    wait = Backoff(0.5, 10.0)
    assert [wait.next() for _ in range(8)] == [0.5, 1.0, 2.0, 4.0, 8.0, 10.0, 10.0, 10.0]
    wait.reset()
    assert wait.current == 0.5 and wait.next() == 0.5 and wait.current == 1.0


@pytest.mark.parametrize("first, cap", [(0, 1), (-1, 1), (2, 1)])
def test_bad_delays_are_refused(first, cap):
    with pytest.raises(ArgumentError, match="first <= cap"):
        Backoff(first, cap)
