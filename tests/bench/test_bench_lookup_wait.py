"""The wait benchmark's harness, small: each waiting Lookup is answered by the Publish request
that brings its data, and its row has the table's shape."""
from tests.bench import bench_lookup_wait as bw


def test_each_wait_is_answered_and_timed():
    (row,) = bw.rows(5)
    assert row[0].startswith("Publish") and row[3] == "ms"
    assert 0.0 < float(row[1]) <= float(row[2])
    assert "5 waits" in row[4]
