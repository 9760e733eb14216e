"""service/world_ticks.py: ticks fall due on measurement time, waiting for the slower sources up
to max_delay, each once, none before the window, and a recording of arrivals replays to the same
ticks. (Rate 0, one answer per body a request, is the hub's: tests/test_hub.py.)"""
import math

import numpy as np
import pytest

from dqpose.world_ticks import Schedule, first_tick, horizon, tick_time


def test_horizon_waits_for_the_slowest_source_up_to_max_delay():
    assert horizon({}, 0.1) == -math.inf
    assert horizon({"cam": 1.0, "arm": 1.05}, 0.1) == 1.0
    # the arm 0.3 s ahead: the camera is waited for only 0.1 s
    assert horizon({"cam": 1.0, "arm": 1.3}, 0.1) == pytest.approx(1.2)


class Body:
    """One body's sources' newest taken times, as a world keeps them, and its window's oldest:
    what a step hands a :class:`Schedule`."""

    def __init__(self, schedule: Schedule, max_delay: float, window: float = math.inf):
        self.schedule, self.max_delay, self.window = schedule, max_delay, window
        self.newest: dict[str, float] = {}
        self.taken: list[float] = []

    def arrive(self, *measurements: tuple[str, float]) -> list[float]:
        """The ticks due after a step bringing ``(source, taken)`` measurements."""
        for source, taken in measurements:
            self.newest[source] = max(self.newest.get(source, -math.inf), taken)
            self.taken.append(taken)
        top = max(self.taken)
        floor = min(t for t in self.taken if t >= top - self.window)
        ks = self.schedule.due("b", horizon(self.newest, self.max_delay), floor)
        return [self.schedule.time("b", k) for k in ks]


def schedule(rate: float) -> Schedule:
    s = Schedule(rate)
    s._phase["b"] = 0.0         # ticks on the plain grid k / rate
    return s


def test_a_fast_arm_does_not_fire_ticks_before_the_camera_arrives():
    t = Body(schedule(10.0), max_delay=0.1)
    assert t.arrive(("cam", 0.0)) == [0.0]
    # the arm runs at 500 Hz; the camera is 50 ms behind: no tick past the camera's time
    due = [x for k in range(1, 40) for x in t.arrive(("arm", k * 0.002))]
    assert due == []
    assert t.arrive(("cam", 0.1)) == []                # the arm is at 0.078 now
    assert t.arrive(("arm", 0.1)) == [pytest.approx(0.1)]


def test_a_silent_source_is_waited_for_max_delay_only():
    t = Body(schedule(10.0), max_delay=0.1)
    t.arrive(("cam", 0.0), ("arm", 0.0))
    assert t.arrive(("arm", 0.15)) == []              # horizon 0.05: cam is waited for
    assert t.arrive(("arm", 0.2)) == [pytest.approx(0.1)]   # 0.1 s past: not waited any longer


def test_each_tick_once_in_order_and_a_late_measurement_fires_nothing_old():
    t = Body(schedule(10.0), max_delay=0.05)
    fired = []
    for time in (0.0, 0.12, 0.31, 0.05, 0.4):       # 0.05 arrives late
        fired += t.arrive(("cam", time))
    assert fired == pytest.approx([0.0, 0.1, 0.2, 0.3, 0.4])


def test_a_gap_longer_than_the_window_skips_the_ticks_without_data():
    t = Body(schedule(10.0), max_delay=0.0, window=0.25)
    t.arrive(("cam", 0.0))
    assert t.arrive(("cam", 4.8), ("cam", 5.0)) == pytest.approx([4.8, 4.9, 5.0])


def test_a_leap_of_the_horizon_is_a_range_not_a_loop():
    s = schedule(1000.0)
    assert list(s.due("b", 0.0, 0.0)) == [0]
    due = s.due("b", 1e6, 0.0)       # a billion ticks: counted, not listed
    assert isinstance(due, range) and (due.start, due.stop) == (1, 10**9 + 1)
    assert s.time("b", due[-1]) == 1e6 and not s.due("b", 1e6, 0.0)


def test_phase_shifts_the_grid():
    s = Schedule(10.0)
    s._phase["b"] = 0.25
    assert not s.due("b", 0.0, 0.0)
    assert [s.time("b", k) for k in s.due("b", 0.03, 0.0)] == [pytest.approx(0.025)]
    assert tick_time(first_tick(0.03, 10.0, 0.25), 10.0, 0.25) == pytest.approx(0.125)


def test_a_recording_of_arrivals_replays_to_the_same_ticks():
    rng = np.random.default_rng(3)
    arrivals = []
    for k in range(400):   # three sources with their own rates, delays and jitter
        s = ("cam1", "cam2", "arm")[k % 3]
        arrivals.append((s, k * 0.01 - (0.04 if s == "cam2" else 0.0) + rng.normal(0, 0.003)))
    runs = []
    for _ in range(2):
        t = Body(Schedule(30.0), max_delay=0.1)
        runs.append([(i, x) for i, a in enumerate(arrivals) for x in t.arrive(a)])
    assert runs[0] == runs[1] and len(runs[0]) > 50
    times = [x for _, x in runs[0]]
    assert times == sorted(times) and len(set(times)) == len(times)


@pytest.mark.parametrize("rate", [-1.0, 0.0, math.nan])
def test_a_schedule_needs_a_rate(rate):
    with pytest.raises(ValueError, match="rate"):
        Schedule(rate)
