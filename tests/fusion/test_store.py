"""dqpose.fusion.store: each body's rows found through its own index are the rows a scan of the
whole store finds, in arrival order, through growth, compaction and a body's removal; those taken
since a time, found from the index's running maximum of taken, too; and a tracker's window ending
at any time, found that way, is the one its definition gives under a cap."""
import numpy as np

from dqpose import limits
from dqpose.fusion import Rows, Source, Tracker
from dqpose.fusion.bounds import TrackerBounds
from dqpose.fusion.store import Store


def _scan(s: Store, b: int, newest, window: float, cap=None) -> np.ndarray:
    rows = np.flatnonzero((s.body[:s.n] == b) & (s.taken[:s.n] >= newest[b] - window))
    return rows if cap is None or len(rows) <= cap else rows[len(rows) - cap:]


def _append(s: Store, newest, window: float, body, taken) -> None:
    """Rows of ``body`` taken at ``taken`` into ``s`` as a tracker without bounds takes them
    (``_index.ingest``, newest updated), every one taken in."""
    m = len(body)
    s.reserve(m, newest, window)
    ok = np.ones(m, bool)
    codes = {b: b for b in range(len(newest))}          # bodies named by their codes
    refused, _, _ = s.index.ingest(
        s, newest, np.full((len(newest), 1), -np.inf), np.zeros(1), np.asarray(body).tolist(),
        codes, ["s"] * m, {"s": 0}, np.arange(m), taken, np.tile(np.eye(1, 8)[0], (m, 1)),
        np.tile(np.eye(6), (m, 1, 1)), ok, None, None, window, -1, np.inf, np.inf, -1, None,
        False)
    assert not refused and ok.all()


def test_rows_by_index_equal_a_scan_through_growth_compaction_and_removal():
    rng = np.random.default_rng(0)
    s = Store(capacity=8)
    bodies, window = 7, 0.5
    newest = np.full(bodies, -np.inf)
    t = 0.0
    for step in range(400):
        # messages of one row (the plain path) and of many (the grouped path), bodies repeating
        m = int(rng.choice([1, 3, 40]))
        body = rng.integers(0, bodies, m)
        taken = t + rng.uniform(-0.3, 0.0, m)        # out of order within the window
        t += 0.01
        _append(s, newest, window, body, taken)
        if step == 250:
            s.keep(s.body[:s.n] != 3)                 # a body removed
            newest[3] = -np.inf
        for b in range(bodies):
            for cap in (None, 5):
                assert np.array_equal(s.rows(b, newest, window, cap),
                                      _scan(s, b, newest, window, cap)), (step, b, cap)
    assert s.n < 400 * 40 / 4      # compacted on the way: rows out of their window were dropped


def test_rows_taken_since_a_time_by_the_running_maximum_equal_a_scan():
    rng = np.random.default_rng(1)
    s = Store(capacity=8)
    newest = np.full(3, -np.inf)
    for step in range(300):
        m = int(rng.choice([1, 5, 30]))
        body = rng.integers(0, 3, m)
        # mostly in order, some rows late by up to a second
        taken = step * 0.01 - rng.exponential(0.02, m) * (rng.random(m) < 0.9) \
            - rng.uniform(0, 1.0, m) * (rng.random(m) < 0.1)
        _append(s, newest, 2.0, body, taken)
        for b in range(3):
            lo = newest[b] - rng.uniform(0, 2.5)
            scan = np.flatnonzero((s.body[:s.n] == b) & (s.taken[:s.n] >= lo))
            assert np.array_equal(s.since(b, lo), scan), (step, b)


def _rows_ending_by_definition(t: Tracker, body: str, end: float, window: float):
    """The rows of the body's window (its last cap), those in [end - window, end], the last
    cap: what Tracker.rows_ending gives, found by scanning the whole window."""
    rows = t._rows(body)
    taken = t.taken_of(rows)
    mine = rows[(taken >= end - window) & (taken <= end)]
    return mine if t.cap is None or len(mine) <= t.cap else mine[len(mine) - t.cap:]


def test_a_window_found_by_the_running_maximum_equals_its_definition_under_a_cap():
    """A buffer of 2 s, windows of 0.2 s ending anywhere in it, a cap of 25 rows a body that the
    buffer exceeds (the cap of the buffer's rows decides), rows late by up to 1.5 s."""
    rng = np.random.default_rng(2)
    bounds = TrackerBounds.of(limits.Limits(max_window=25))
    t = Tracker(2.0, sources=[Source("cam")], bounds=bounds)
    assert t.cap == 25
    ident = np.array([1.0, 0, 0, 0, 0, 0, 0, 0])
    for step in range(400):
        m = int(rng.choice([1, 4, 20]))
        bodies = [f"b{k}" for k in rng.integers(0, 2, m)]
        times = step * 0.01 - rng.uniform(0, 1.5, m) * (rng.random(m) < 0.15)
        t.ingest(Rows(bodies, ["cam"] * m, times, np.tile(ident, (m, 1)),
                      np.tile(np.eye(6) * 1e-4, (m, 1, 1))))
        for body in t.bodies:
            end = t.newest(body) - rng.choice([0.0, rng.uniform(0, 2.0)])
            for window in (0.05, 0.2, 2.5):
                assert np.array_equal(t.rows_ending(body, end, window),
                                      _rows_ending_by_definition(t, body, end, window)), \
                    (step, body, window)
