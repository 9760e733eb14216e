"""A new user's arm session: ``dqpose serve --sims`` (``make run``), which serves the simulated UR
and PiPER as the arms ``ur`` and ``piper`` (``--arm ur=ur:sim --arm piper=piper:sim``: no bus
name to look up), ``dqpose arm list`` / ``dqpose arm get`` to see where they are, and a plan run
from there (``Client.execute(..., from_current=True)``). The real command in its own process, the
real ur_rtde and python-can against the simulators it started."""
from __future__ import annotations

import json
import signal

import numpy as np
import pytest

from dqpose import dq, trajectory
from dqpose.rpc.client import Client
from tests.cli._cli import run, server, serving  # noqa: F401 (server: a fixture)

LIMITS = trajectory.Limits(0.1, 0.5, 0.5, 1.0, 5.0, 10.0)


@pytest.fixture(scope="module")
def served():
    pytest.importorskip("rtde_control")
    pytest.importorskip("msgpack")
    proc, events = serving("--sims")       # make run's flags
    try:
        yield events, events[-1]["address"]
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=30) == 0
        log = proc.stderr.read()
        for bad in ("Traceback", "Event loop is closed", "leaked"):
            assert bad not in log, log
    finally:
        if proc.poll() is None:
            proc.kill()


def test_sim_targets_are_the_simulators_started(served):
    events, _ = served
    sims = {e["device"]: e for e in events if e.get("event") == "simulator"}
    arms = {e["name"]: e for e in events if e.get("event") == "arm"}
    assert arms["ur"]["spec"] == sims["ur"]["spec"]
    assert arms["piper"]["spec"] == sims["piper"]["spec"]


def test_arm_list_is_a_table_of_every_arm(served, capsys):
    _, target = served
    code, out, err = run(capsys, "arm", "list", "--server", target)
    assert (code, err) == (0, "")
    header, *rows = out.splitlines()
    assert header.split()[:3] == ["ARM", "STATE", "BUSY"]
    assert [r.split()[0] for r in rows] == ["piper", "ur"]
    with Client(target) as c:
        for row, arm in zip(rows, c.list_arms()):
            x, y, z = (float(v) for v in row.split()[3:6])
            assert np.allclose([x, y, z], dq.to_pose(arm.pose)[1], atol=1e-4)
            assert row.split()[-1] == "none"         # no faults
            # an arm that has run no plan yet is idle (its run's state once it has one)
            assert row.split()[1] == (arm.state or "idle")
            assert row.split()[2] == ("yes" if arm.busy else "no")


def test_arm_list_on_a_server_without_arms_says_how_to_add_one(server, capsys):
    code, out, err = run(capsys, "arm", "list", "--server", server.target)
    assert (code, err) == (0, "")
    assert out.startswith("no arms: ") and "--arm NAME=KIND:TARGET" in out and "--sims" in out
    code, out, _ = run(capsys, "arm", "list", "--format", "json", "--server", server.target)
    assert (code, json.loads(out)) == (0, [])


def test_arm_get_as_json_then_move_from_there(served, capsys):
    _, target = served
    code, out, err = run(capsys, "arm", "get", "piper", "--format", "json", "--server", target)
    assert (code, err) == (0, "")
    doc = json.loads(out)
    assert doc["arm"] == "piper" and doc["faults"] == [] and doc["busy"] is False
    assert doc["limits"]["max_linear_velocity"] == 0.25
    p, o = doc["pose"]["position"], doc["pose"]["orientation"]
    here = dq.from_pose([o["w"], o["x"], o["y"], o["z"]], [p["x"], p["y"], p["z"]])
    goal = dq.from_pose(dq.to_pose(here)[0], dq.to_pose(here)[1] + [0.02, 0.0, -0.01])
    with Client(target) as c:
        feedback = list(c.execute("piper", [goal], LIMITS, from_current=True))
    assert feedback[-1].state == "FINISHED", feedback[-1]
    code, out, _ = run(capsys, "arm", "get", "piper", "--server", target)
    assert code == 0
    assert out.splitlines()[0] == "arm piper: idle; its run: FINISHED"
    xyz = [float(v) for v in out.splitlines()[2].split(",")[:3]]
    assert np.allclose(xyz, dq.to_pose(goal)[1], atol=1e-3)


def test_an_unknown_arm_is_named_with_the_servers_arms(served, capsys):
    _, target = served
    code, out, err = run(capsys, "arm", "get", "kuka", "--server", target)
    assert (code, out) == (2, "")
    assert err == ("dqpose arm get: error: arm: unknown arm 'kuka' (this server's arms: piper, "
                   "ur)\n")
