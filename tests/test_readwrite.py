"""dqpose.readwrite: readers together, a writer alone, a waiting writer ahead of later readers."""
import threading

from dqpose.readwrite import ReadWrite
from tests._polling import wait_until


def _hold(lock: ReadWrite, how: str, entered: list, name: str, release: threading.Event,
          asking: threading.Event | None = None):
    def run():
        if asking is not None:
            asking.set()
        with getattr(lock, how)():
            entered.append(name)
            release.wait(10.0)
    t = threading.Thread(target=run, daemon=True)
    t.start()
    return t


def _ended(threads) -> bool:
    for t in threads:
        t.join(10.0)
    return not any(t.is_alive() for t in threads)


def test_readers_hold_it_together_and_a_writer_waits_for_them():
    lock, entered = ReadWrite(), []
    first, second, writer = threading.Event(), threading.Event(), threading.Event()
    threads = [_hold(lock, "read", entered, "r1", first)]
    assert wait_until(lambda: entered == ["r1"])
    threads.append(_hold(lock, "read", entered, "r2", second))
    assert wait_until(lambda: entered == ["r1", "r2"])     # beside r1, not after it
    threads.append(_hold(lock, "write", entered, "w", writer))
    assert wait_until(lambda: lock._waiting == 1)
    first.set()
    threads[0].join(10.0)
    assert entered == ["r1", "r2"]                          # r2 still reads
    second.set()
    assert wait_until(lambda: entered == ["r1", "r2", "w"])
    writer.set()
    assert _ended(threads)


def test_a_waiting_writer_goes_before_the_readers_that_came_after_it():
    lock, entered = ReadWrite(), []
    reading, writing, late = threading.Event(), threading.Event(), threading.Event()
    threads = [_hold(lock, "read", entered, "r1", reading)]
    assert wait_until(lambda: entered == ["r1"])
    threads.append(_hold(lock, "write", entered, "w", writing))
    assert wait_until(lambda: lock._waiting == 1)
    asking = threading.Event()
    threads.append(_hold(lock, "read", entered, "r2", late, asking))
    assert asking.wait(10.0)
    # r2 held back while r1 still reads: without the writer waiting it would read beside r1
    assert not wait_until(lambda: "r2" in entered, timeout=0.2)
    reading.set()
    assert wait_until(lambda: entered == ["r1", "w"])
    writing.set()
    assert wait_until(lambda: entered == ["r1", "w", "r2"])
    late.set()
    assert _ended(threads)
