"""`dqpose sim piper` in its own process: a bus that crosses processes without root (python-can's
udp_multicast), reached by name, and a hint when the chosen bus cannot be opened."""
from __future__ import annotations

import os
import random
import subprocess
import sys

import numpy as np
import pytest

from dqpose import dq, drivers
from dqpose.drivers.base import pose_delta

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))


def test_arm_in_another_process_moves_the_simulated_piper():
    pytest.importorskip("msgpack")               # python-can's udp_multicast needs it
    from dqpose.drivers.sim.piper import PiperSimProcess
    group = f"239.74.{random.randrange(256)}.{random.randrange(1, 255)}"
    with PiperSimProcess("udp_multicast", group) as sim, drivers.open_arm(sim.spec) as arm:
        assert sim.spec == f"piper:udp_multicast:{group}"
        _, start = arm.wait_for_feedback(5.0)
        q, t = dq.to_pose(start)
        target = dq.from_pose(q, t + [0.01, -0.01, 0.005])
        arm.move(target, 0.1, 0.5)
        assert pose_delta(arm.tool_pose()[1], target)[0] <= arm.position_tolerance
        assert np.isclose(np.linalg.norm(arm.tool_pose()[1][:4]), 1.0)


def test_default_bus_crosses_processes_and_a_bus_that_cannot_open_gets_a_hint():
    import argparse

    from dqpose.drivers.sim.piper import DEFAULT_CHANNEL, DEFAULT_INTERFACE, add_arguments
    p = argparse.ArgumentParser()
    add_arguments(p)
    args = p.parse_args([])
    assert (args.interface, args.channel) == (DEFAULT_INTERFACE, DEFAULT_CHANNEL) \
        == ("udp_multicast", "239.74.163.2")
    r = subprocess.run([sys.executable, "-m", "dqpose.cli", "sim", "piper", "--interface",
                        "socketcan", "--channel", "no-such-can9"], cwd=ROOT, capture_output=True,
                       text=True, timeout=30)
    assert r.returncode == 2
    assert "dqpose sim piper: cannot open python-can socketcan channel 'no-such-can9'" in r.stderr
    assert "vcan" in r.stderr and "--interface udp_multicast" in r.stderr
