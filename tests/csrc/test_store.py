"""The store's per-body index in C (service/csrc/store.c, ``_dqcore.StoreIndex``) against NumPy:
a body's rows from where the running maximum of taken reaches a time (searchsorted), those taken
since it (a scan), the last cap, the rows a compaction keeps; many bodies; its refusals."""
import numpy as np
import pytest

from dqpose._dqcore import StoreIndex


def test_rows_since_a_time_and_live_rows_equal_numpy_over_many_bodies():
    rng = np.random.default_rng(5)
    n, bodies = 3000, 40                         # the body table grows past its first 16
    body = rng.integers(0, bodies, n)
    taken = np.arange(n) * 1e-3 - rng.exponential(0.01, n) * (rng.random(n) < 0.2)
    x = StoreIndex()
    for lo, hi in ((0, 1), (1, 7), (7, 1000), (1000, n)):      # pushed in pieces, as appended
        x.push(lo, body[lo:hi], taken[lo:hi])
    newest = np.full(bodies, -np.inf)
    np.maximum.at(newest, body, taken)
    for b in range(bodies):
        mine = np.flatnonzero(body == b)
        reach = np.maximum.accumulate(taken[mine])
        assert x.count(b) == len(mine)
        for lo in rng.uniform(-0.1, 3.1, 20):
            start = np.searchsorted(reach, lo)
            assert np.array_equal(x.after(b, lo), mine[start:])
            since = mine[taken[mine] >= lo]
            assert np.array_equal(x.since(b, lo, taken), since)
            assert np.array_equal(x.since(b, lo, taken, 3), since[-3:])
    for window, cap in ((0.5, -1), (0.5, 7), (10.0, 0)):
        live = taken >= newest[body] - window
        if cap >= 0:
            for b in range(bodies):
                mine = np.flatnonzero((body == b) & live)
                live[mine[:max(0, len(mine) - cap)]] = False
        assert np.array_equal(x.live(taken, newest, window, cap, n), live), (window, cap)
    x.reset()
    assert x.count(0) == 0 and len(x.after(0, -np.inf)) == 0 and len(x.after(99, 0.0)) == 0


def test_its_refusals_name_the_argument():
    x = StoreIndex()
    with pytest.raises(ValueError, match="^body: codes are >= 0"):
        x.push(0, np.array([-1]), np.array([0.0]))
    with pytest.raises(ValueError, match="^taken: expected one time a row"):
        x.push(0, np.array([0, 1]), np.array([0.0]))
    x.push(0, np.array([0, 3]), np.array([0.0, 1.0]))
    with pytest.raises(ValueError, match="^newest: a body of the index has none"):
        x.live(np.array([0.0, 1.0]), np.array([0.0]), 1.0, -1, 2)
    with pytest.raises(ValueError, match="^taken: fewer rows than n"):
        x.live(np.array([0.0]), np.zeros(4), 1.0, -1, 2)


def test_a_plain_request_is_one_with_nothing_to_refuse():
    from dqpose._dqcore import store_plain

    def plain(newest, body, times, window=1.0, max_time=100.0, jump=5.0):
        newest = np.array(newest, np.float64)
        t = np.array(times, np.float64)
        return store_plain(newest, np.array(body, np.int64), t, t - 0.0, window, max_time,
                           jump), newest

    ok, newest = plain([0.0, -np.inf], [0, 1, 1], [0.5, 3.0, 3.2])
    assert ok and newest.tolist() == [0.5, 3.2]
    # a new body's rows of one call: its earliest is the reference of the jump rule
    assert not plain([0.0, -np.inf], [1, 1], [3.0, 8.5])[0]
    assert not plain([0.0], [0], [5.5])[0]                          # a jump
    assert not plain([0.0], [0], [101.0], jump=1e9)[0]             # past max_time
    assert not plain([0.0], [0, 0], [2.0, 0.9])[0]                  # late: 1.1 s before 2.0
    assert plain([0.0], [0, 0], [2.0, 1.0])[0]                      # exactly the window: kept
    assert not plain([0.0], [1], [0.0])[0]                          # a body beyond newest
    with pytest.raises(ValueError, match="^newest: expected a writeable contiguous float64"):
        store_plain(np.zeros(3, np.float32), np.zeros(1, np.int64), np.zeros(1), np.zeros(1),
                    1.0, 1.0, 1.0)
