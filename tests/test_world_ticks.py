"""service/world_ticks.py: ticks fall due on measurement time, waiting for the slower sources up
to max_delay, each once, and a recording of arrivals replays to the same ticks."""
import math

import numpy as np
import pytest

from dqpose.world_ticks import MAX_DUE, Ticks, first_tick, horizon, tick_time


def test_horizon_waits_for_the_slowest_source_up_to_max_delay():
    assert horizon({}, 0.1) == -math.inf
    assert horizon({"cam": 1.0, "arm": 1.05}, 0.1) == 1.0
    # the arm 0.3 s ahead: the camera is waited for only 0.1 s
    assert horizon({"cam": 1.0, "arm": 1.3}, 0.1) == pytest.approx(1.2)


def test_a_fast_arm_does_not_fire_ticks_before_the_camera_arrives():
    t = Ticks(rate=10.0, max_delay=0.1)
    assert t.arrive("cam", 0.0) == [0.0]
    # the arm runs at 500 Hz; the camera is 50 ms behind: no tick past the camera's time
    due = [x for k in range(1, 40) for x in t.arrive("arm", k * 0.002)]
    assert due == []
    assert t.arrive("cam", 0.1) == []                # the arm is at 0.078 now
    assert t.arrive("arm", 0.1) == [pytest.approx(0.1)]


def test_a_silent_source_is_waited_for_max_delay_only():
    t = Ticks(rate=10.0, max_delay=0.1)
    t.arrive("cam", 0.0)
    t.arrive("arm", 0.0)
    assert t.arrive("arm", 0.15) == []              # horizon 0.05: cam is waited for
    assert t.arrive("arm", 0.2) == [pytest.approx(0.1)]   # 0.1 s past: not waited any longer


def test_each_tick_once_in_order_and_a_late_measurement_fires_nothing_old():
    t = Ticks(rate=10.0, max_delay=0.05)
    fired = []
    for time in (0.0, 0.12, 0.31, 0.05, 0.4):       # 0.05 arrives late
        fired += t.arrive("cam", time)
    assert fired == pytest.approx([0.0, 0.1, 0.2, 0.3, 0.4])


def test_rate_zero_answers_each_measurement_time_once_the_horizon_reaches_it():
    t = Ticks(rate=0.0, max_delay=0.1)
    assert t.arrive("cam", 1.0) == [1.0]
    assert t.arrive("arm", 1.0) == []                # the same time: answered already
    assert t.arrive("arm", 1.02) == []               # cam has not reached 1.02
    assert t.arrive("arm", 1.04) == []
    assert t.arrive("cam", 1.03) == [1.02, 1.03]
    assert t.arrive("arm", 1.5) == [1.04]            # 1.5 - 0.1 = 1.4 passes 1.04 only
    assert t.pending == [1.5]


def test_a_gap_longer_than_the_window_skips_the_ticks_without_data():
    t = Ticks(rate=10.0, max_delay=0.0, window=0.25)
    t.arrive("cam", 0.0)
    assert t.arrive("cam", 5.0) == pytest.approx([4.8, 4.9, 5.0])


def test_an_arrival_makes_at_most_max_due_ticks_due():
    t = Ticks(rate=1000.0, max_delay=0.0)
    t.arrive("cam", 0.0)
    due = t.arrive("cam", 1e4)
    assert len(due) == MAX_DUE and due[-1] == 1e4


def test_phase_shifts_the_grid():
    t = Ticks(rate=10.0, max_delay=0.0, phase=0.25)
    assert t.arrive("cam", 0.0) == []
    assert t.arrive("cam", 0.03) == [pytest.approx(0.025)]
    assert tick_time(first_tick(0.03, 10.0, 0.25), 10.0, 0.25) == pytest.approx(0.125)


@pytest.mark.parametrize("rate", [0.0, 30.0])
def test_a_recording_of_arrivals_replays_to_the_same_ticks(rate):
    rng = np.random.default_rng(3)
    arrivals = []
    for k in range(400):   # three sources with their own rates, delays and jitter
        s = ("cam1", "cam2", "arm")[k % 3]
        arrivals.append((s, k * 0.01 - (0.04 if s == "cam2" else 0.0) + rng.normal(0, 0.003)))
    runs = []
    for _ in range(2):
        t = Ticks(rate, max_delay=0.1)
        runs.append([(i, x) for i, (s, time) in enumerate(arrivals) for x in t.arrive(s, time)])
    assert runs[0] == runs[1] and len(runs[0]) > 50
    times = [x for _, x in runs[0]]
    assert times == sorted(times) and len(set(times)) == len(times)


@pytest.mark.parametrize("kw, text", [(dict(rate=-1.0, max_delay=0.1), "rate"),
                                      (dict(rate=1.0, max_delay=math.nan), "max_delay")])
def test_bad_arguments_are_named(kw, text):
    with pytest.raises(ValueError, match=text):
        Ticks(**kw)
