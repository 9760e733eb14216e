"""The simulated UR controller's cycle (drivers.sim.ur.server) on a virtual clock: time a starved
machine took from it is caught up by the model (the arm moves on as a real one would), up to
CATCH_UP, and streamed from then on without a burst."""
from __future__ import annotations

import numpy as np
import pytest

from dqpose.drivers.sim.ur import server
from dqpose.drivers.sim.ur.server import CATCH_UP, URSim


class _Clock:
    """time.monotonic and time.sleep of a clock that only moves when told."""

    def __init__(self):
        self.now = 0.0

    def monotonic(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.now += seconds


def _run(monkeypatch, stall: float, ticks: int = 1000):
    """The cycle for ``ticks`` ticks with one stall of ``stall`` s at tick 100; the sim, the
    clock and how many packets it streamed."""
    clock = _Clock()
    monkeypatch.setattr(server, "time", clock)
    sim = URSim()
    sim._servers = []           # no sockets: the cycle alone
    streamed = []
    monkeypatch.setattr(sim, "_stream", lambda values: streamed.append(sim.tick))
    step = sim.step

    def stepped():
        values = step()
        if sim.tick == 100:
            clock.now += stall          # the process was not scheduled for `stall` s
        if sim.tick >= ticks:
            sim.stopping.set()
        return values

    monkeypatch.setattr(sim, "step", stepped)
    sim.serve_forever()
    return sim, clock, streamed


@pytest.mark.parametrize("stall", [0.3, 1.0])
def test_the_model_catches_up_on_time_a_stall_took_up_to_catch_up(monkeypatch, stall):
    sim, clock, streamed = _run(monkeypatch, stall)
    lag = clock.now - sim.tick * sim.dt          # wall time the model did not live through
    assert lag == pytest.approx(max(0.0, stall - CATCH_UP), abs=2 * sim.dt)
    # the missed cycles were stepped, not streamed: no burst of packets after the stall
    missed = min(stall, CATCH_UP) / sim.dt
    assert len(streamed) == pytest.approx(sim.tick - missed, abs=2)


def test_a_servoing_arm_moves_on_through_a_stall(monkeypatch):
    """An arm servoing towards a far set-point has covered the stall's distance when the stream
    resumes, as a real arm would have."""
    moved = {}
    for stall in (0.0, 0.3):
        clock = _Clock()
        monkeypatch.setattr(server, "time", clock)
        sim = URSim()
        sim._servers = []
        monkeypatch.setattr(sim, "_stream", lambda values: None)
        sim.servoing, sim.servo_target = True, (sim.p + np.array([0.5, 0.0, 0.0]), sim.q.copy())
        p0 = sim.p.copy()
        step = sim.step

        def stepped(sim=sim, step=step, clock=clock, stall=stall):
            values = step()
            if sim.tick == 10:
                clock.now += stall
            if clock.now >= 0.4:
                sim.stopping.set()
            return values

        monkeypatch.setattr(sim, "step", stepped)
        sim.serve_forever()
        moved[stall] = float(np.linalg.norm(sim.p - p0))
    # the same wall time, the same distance, stall or not (within two cycles at full speed)
    assert moved[0.3] == pytest.approx(moved[0.0], abs=2 * sim.cfg.max_linear_speed * sim.dt)
