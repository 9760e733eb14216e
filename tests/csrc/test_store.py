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


def test_ingest_refuses_columns_and_codes_it_cannot_write():
    from dqpose.fusion.store import Store
    s = Store(capacity=4)
    newest, seen, latency = np.full(2, -np.inf), np.full((2, 1), -np.inf), np.zeros(1)

    def ingest(store=s, body=(0,), ok=None, newest=newest, names=None):
        m = len(body)
        return store.index.ingest(
            store, newest, seen, latency, list(body) if names is None else names,
            {0: 0, 1: 1, 2: 2}, ["s"] * m, {"s": 0}, np.arange(m), np.zeros(m),
            np.tile(np.eye(1, 8)[0], (m, 1)), np.tile(np.eye(6), (m, 1, 1)),
            np.ones(m, bool) if ok is None else ok, None, None, 1.0, -1, np.inf, np.inf, -1,
            None, False)

    with pytest.raises(ValueError, match="^rows: a code out of range"):
        ingest(body=(2,))                                   # no such body in newest
    with pytest.raises(ValueError, match="^rows: a code out of range, or the store's columns"):
        ingest(body=(0,) * 5)                               # 5 rows, room for 4
    assert s.n == 0
    with pytest.raises(ValueError, match="^ok: expected one a row"):
        ingest(names=[0, 0])
    with pytest.raises(ValueError, match="^ids: expected 2 rows"):
        ingest(names=[0, 0], ok=np.ones(2, bool))
    with pytest.raises(ValueError, match="^ok: expected a writeable contiguous 1-d array"):
        ingest(ok=np.ones(1, np.int8))
    with pytest.raises(ValueError, match="^newest: expected a writeable contiguous 1-d array"):
        ingest(newest=np.zeros(2, np.float32))
    short = Store(capacity=4)
    short.taken = np.zeros(3)
    with pytest.raises(ValueError, match="^store.taken: expected a writeable contiguous column"):
        ingest(store=short)
    assert ingest(body=(3,)) is None and s.n == 0          # a name not coded: nothing done
    assert ingest() == ([], True, (0,)) and s.n == 1 and newest.tolist() == [0.0, -np.inf]
