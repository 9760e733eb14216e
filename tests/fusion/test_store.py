"""dqpose.fusion.store: each body's rows found through its own index are the rows a scan of the
whole store finds, in arrival order, through growth, compaction and a body's removal."""
import numpy as np

from dqpose.fusion.store import _Store


def _scan(s: _Store, b: int, newest, window: float, cap=None) -> np.ndarray:
    rows = np.flatnonzero((s.body[:s.n] == b) & (s.taken[:s.n] >= newest[b] - window))
    return rows if cap is None or len(rows) <= cap else rows[len(rows) - cap:]


def test_rows_by_index_equal_a_scan_through_growth_compaction_and_removal():
    rng = np.random.default_rng(0)
    s = _Store(capacity=8)
    bodies, window = 7, 0.5
    newest = np.full(bodies, -np.inf)
    t = 0.0
    for step in range(400):
        # messages of one row (the plain path) and of many (the grouped path), bodies repeating
        m = int(rng.choice([1, 3, 40]))
        body = rng.integers(0, bodies, m)
        taken = t + rng.uniform(-0.3, 0.0, m)        # out of order within the window
        t += 0.01
        np.maximum.at(newest, body, taken)
        s.append(newest, window, None, ids=np.arange(m), body=body, codes=np.zeros(m, int),
                 times=taken, taken=taken, poses=np.zeros((m, 8)), covs=np.zeros((m, 6, 6)),
                 wposes=np.zeros((m, 8)))
        if step == 250:
            s.keep(s.body[:s.n] != 3)                 # a body removed
            newest[3] = -np.inf
        for b in range(bodies):
            for cap in (None, 5):
                assert np.array_equal(s.rows(b, newest, window, cap),
                                      _scan(s, b, newest, window, cap)), (step, b, cap)
    assert s.n < 400 * 40 / 4      # compacted on the way: rows out of their window were dropped
