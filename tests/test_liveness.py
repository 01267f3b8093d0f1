"""robot_change.service.liveness: progress stamps, units of work, the verdict (a fake clock)."""

from __future__ import annotations

import threading

import pytest

from robot_change.errors import InputError
from robot_change.service.daemon import DEFAULT_STALL_S, MIN_STALL_S, stall_bound
from robot_change.service.liveness import Progress


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


@pytest.fixture
def clock() -> Clock:
    return Clock()


def test_a_part_that_keeps_beating_is_never_stalled(clock):
    p = Progress(5.0, clock=clock)
    for _ in range(20):
        p.beat("link")
        clock.t += 4.9
        assert p.stalled() == ""


def test_a_silent_part_is_stalled_after_its_bound(clock):
    p = Progress(5.0, {"camera": 8.0}, clock=clock)
    p.beat("link")
    p.beat("camera")
    clock.t += 5.0
    assert p.stalled() == ""  # at the bound, not past it
    clock.t += 0.1
    assert p.stalled() == "link: no progress for 5.1 s"
    p.beat("link")
    clock.t += 3.0
    assert p.stalled() == "camera: no progress for 8.1 s"


def test_unwatched_and_forgotten_parts_never_stall(clock):
    p = Progress(1.0, clock=clock)
    assert not p.watches("watch")
    p.beat("watch")
    assert p.watches("watch")
    p.forget("watch")
    clock.t += 100.0
    assert p.stalled() == "" and not p.watches("watch")


def test_work_must_end_within_the_bound_and_ending_it_is_progress(clock):
    p = Progress(5.0, clock=clock)
    token = p.begin("detector", "WATCH office: the check of frame 7")
    clock.t += 5.5
    assert p.stalled() == ("detector: WATCH office: the check of frame 7 has not finished "
                           "after 5.5 s")
    p.end(token)
    assert p.stalled() == ""
    assert not p.watches("detector")  # a part of units of work alone need not beat
    clock.t += 100.0
    assert p.stalled() == ""
    p.end(token)  # twice is harmless


def test_the_end_of_work_is_progress_of_a_watched_part(clock):
    p = Progress(5.0, clock=clock)
    p.beat("control")
    clock.t += 4.0
    token = p.begin("control", "CHECK office")
    clock.t += 4.0  # 8 s since the beat, 4 s of work: judged by the work
    assert p.stalled() == ""
    p.end(token)
    clock.t += 4.0
    assert p.stalled() == ""


def test_overdue_work_is_named_before_a_silent_part(clock):
    p = Progress(2.0, clock=clock)
    p.beat("control")
    p.begin("control", "CHECK office")
    clock.t += 10.0
    assert p.stalled().startswith("control: CHECK office has not finished")


def test_the_most_overdue_is_named(clock):
    p = Progress(2.0, {"watch": 3.0}, clock=clock)
    p.beat("watch")
    clock.t += 1.0
    p.beat("link")
    clock.t += 3.0
    assert p.stalled() == "watch: no progress for 4.0 s"  # 1.0 past its bound, link 1.0 too
    p.set_bound("watch", 10.0)
    assert p.stalled() == "link: no progress for 3.0 s"


def test_progress_is_thread_safe():
    p = Progress(60.0)

    def work():
        for _ in range(2000):
            p.end(p.begin("detector", "x"))
            p.beat("link")

    threads = [threading.Thread(target=work) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert p.stalled() == "" and p._work == {}


@pytest.mark.parametrize("bound", [0, -1.0, float("nan")])
def test_a_bound_must_be_positive(bound):
    with pytest.raises(InputError, match="bound_s"):
        Progress(bound)


@pytest.mark.parametrize("interval, expected", [(None, DEFAULT_STALL_S), (5.0, 5.0),
                                                (0.5, MIN_STALL_S), (30.0, 30.0)])
def test_the_stall_bound_is_half_of_watchdogsec_with_a_floor(interval, expected):
    assert stall_bound(interval) == expected


def test_a_unit_of_work_may_have_a_bound_of_its_own():
    now = [0.0]
    progress = Progress(1.0, clock=lambda: now[0])
    slow = progress.begin("control", "CAPTURE_REFERENCE dock", bound_s=3.0)
    quick = progress.begin("link", "a turn")
    now[0] = 2.0
    assert progress.stalled() == "link: a turn has not finished after 2.0 s"
    progress.end(quick)
    assert progress.stalled() == ""  # the capture is within its own 3 s
    now[0] = 3.5
    assert progress.stalled() == "control: CAPTURE_REFERENCE dock has not finished after 3.5 s"
    progress.end(slow)
    assert progress.stalled() == ""
