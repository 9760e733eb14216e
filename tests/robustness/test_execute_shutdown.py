"""``dqpose serve`` stopped (SIGTERM) while an arm executes a plan (S1): a plan that cannot end
within the drain and grace is brought to a controlled stop at once, and its call ends with a
last record and a status (not cut); one that can end is let finish. The server exits 0 with
nothing after its last log line, the arm at rest. The real command, the shipped Client, the
simulated UR through ur_rtde."""
from __future__ import annotations

import json
import signal

import pytest

from dqpose.rpc.client import Client, RpcError
from tests.cli._cli import serving
from tests.robustness._arms import SLOW, distance, offset


@pytest.fixture
def ur():
    pytest.importorskip("rtde_control")
    from dqpose.drivers.sim.ur import URSimProcess
    with URSimProcess() as sim:
        sim.set_pose([0.4, -0.1, 0.3, 2.2, 2.2, 0.0])
        yield sim


def _here(sim):
    from dqpose.drivers.rotvec import pose_from_rotvec
    return pose_from_rotvec(sim.state()["pose"])


@pytest.mark.parametrize("dx, ends", [(0.1, "STOPPED"), (0.004, "FINISHED")],
                         ids=["too-long-for-the-grace", "ends-within-the-grace"])
def test_sigterm_during_an_execute(ur, dx, ends):
    start = _here(ur)
    goal = offset(start, dx=dx)          # 0.1 m at SLOW: ~5 s, past drain + grace
    proc, events = serving("--arm", f"ur=ur:{ur.host}", "--drain", "0.2", "--grace", "1")
    address = events[-1]["address"]
    try:
        got, err = [], None
        with Client(address) as c:
            it = c.execute("ur", [start, goal], SLOW)
            got.append(next(it))
            proc.send_signal(signal.SIGTERM)
            try:
                for fb in it:
                    got.append(fb)
            except RpcError as e:
                err = e
        assert proc.wait(timeout=30) == 0
        log = proc.stderr.read()
    finally:
        if proc.poll() is None:
            proc.kill()
    assert got[-1].state == ends, (got[-1], err)
    if ends == "STOPPED":
        assert err is not None and err.code.name == "UNAVAILABLE"
        assert err.feedback is got[-1] and "shutting down" in got[-1].message
        assert distance(got[-1].actual, goal) > 0.05        # stopped, not run to the end
    else:
        assert err is None and distance(_here(ur), goal) < 1e-4
    st = ur.state()
    assert not st["servoing"] and not st["moving"]
    # the last line is the server's own: no thread left to log after it
    assert json.loads(log.strip().splitlines()[-1])["event"] == "stopped", log
    for bad in ("Traceback", "Event loop is closed", "leaked"):
        assert bad not in log, log
