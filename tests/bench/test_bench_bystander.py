"""The bystander benchmark's attacks (``tests/bench/attacks.py``), each for a second against a
real ``dqpose serve`` process started as its row starts it, beside the traffic it meets: the
server refuses or bounds each as its row expects, and the ordinary producer and subscriber go
on unharmed (acks and answers, no error)."""
from __future__ import annotations

import contextlib
import threading
import time
from collections import Counter

import pytest

from tests.bench.attacks import ATTACKS, FED, Unavailable, said, served, surprises
from tests.bench.bench_grpc import ServerProcess

#: how long each attack's background runs before it, s
LEAD = 0.5


@pytest.fixture(scope="module")
def servers(tmp_path_factory):
    """setup -> the Served of a server of that setup (or the Unavailable that kept it from
    starting), every setup's started at once, all stopped (and their mounts undone) at the
    end."""
    setups = list(dict.fromkeys(a.setup for a in ATTACKS.values()))
    made: dict = {}
    with contextlib.ExitStack() as stack:
        processes = []

        def start(setup, s):
            processes.append(ServerProcess("aio", quiet_log=True, extra=s.flags))
            made[setup] = served(processes[-1].target, processes[-1].events, s)

        starting = []
        for setup in setups:
            try:
                s = stack.enter_context(setup(str(tmp_path_factory.mktemp("setup"))))
            except Unavailable as e:
                made[setup] = e
                continue
            starting.append(threading.Thread(target=start, args=(setup, s)))
            starting[-1].start()
        for t in starting:
            t.join()

        def stop():
            for p in processes:
                p.proc.terminate()
            for p in processes:
                p.stop()
        stack.callback(stop)
        yield made


def _in_thread(fn, *args, **kw):
    got: Counter = Counter()
    t = threading.Thread(target=lambda: got.update(fn(*args, **kw)), daemon=True)
    t.start()
    return t, got


@pytest.mark.parametrize("name", ATTACKS, ids=[n.split(":")[0] for n in ATTACKS])
def test_the_server_refuses_or_bounds_the_attack_as_its_row_expects(servers, name):
    attack = ATTACKS[name]
    target = servers[attack.setup]
    if isinstance(target, Unavailable):
        pytest.skip(str(target))
    quiet, stop = threading.Event(), threading.Event()
    if attack.background is not None:
        fed, fed_got = _in_thread(attack.background, target, quiet)
        time.sleep(LEAD)
    attacker, got = _in_thread(attack.attack, target, stop, **attack.quick)
    time.sleep(attack.quick_seconds)
    stop.set()
    attacker.join(60)
    quiet.set()
    assert not attacker.is_alive()
    assert not surprises(got, attack.expected, attack.allowed), said(got)
    if attack.background is not None:
        fed.join(30)
        assert not surprises(fed_got, FED), said(fed_got)
