"""``dqpose serve``'s options: a value out of range is one line naming the flag and the allowed
range, exit code 2, and no server (the ranges themselves live in ``ServerConfig``)."""
from __future__ import annotations

import json
import subprocess
import sys

import pytest

from tests.cli._cli import ROOT, serving


@pytest.mark.parametrize("flags, message", [
    (["--port", "116686"], "--port: must be within 0..65535, got 116686"),
    (["--port", "-1"], "--port: must be within 0..65535, got -1"),
    (["--metrics-port", "70000"], "--metrics-port: must be within 1..65535, got 70000"),
    (["--max-message-bytes", "-1"], "--max-message-bytes: must be within 1..2147483647, got -1"),
    (["--max-poses", "0"], "--max-poses: must be within 1..2147483647, got 0"),
    (["--max-poses", "-5"], "--max-poses: must be within 1..2147483647, got -5"),
    (["--grace", "-1"], "--grace: must be a finite number of seconds >= 0, got -1"),
    (["--drain", "nan"], "--drain: must be a finite number of seconds >= 0, got nan"),
    (["--keepalive", "0"], "--keepalive: must be within 0.001..2147483 seconds, got 0"),
    (["--replica-name", "cell a"],
     "--replica-name: only printable ASCII without spaces, got 'cell a'"),
    (["--replica-name", ""], "--replica-name: must not be empty"),
])
def test_an_option_out_of_range_is_one_line_naming_the_flag_and_exit_2(flags, message):
    res = subprocess.run([sys.executable, "-m", "dqpose.cli", "serve", *flags],
                         capture_output=True, text=True, timeout=30, cwd=ROOT)
    assert (res.returncode, res.stderr) == (2, f"dqpose serve: error: {message}\n")
    assert res.stdout == ""


GRAMMAR = "NAME=KIND:TARGET[?key=value&key=value...]"


@pytest.mark.parametrize("value, message", [
    ("ur", f"--arm: expected {GRAMMAR} (e.g. ur=ur:192.168.1.10), got 'ur'"),
    ("=ur:host", f"--arm: expected {GRAMMAR} (e.g. ur=ur:192.168.1.10), got '=ur:host'"),
    ("my arm=ur:host", "--arm: the name 'my arm' must be a word (letters, digits, _)"),
    (["ur=ur:host", "--arm-realtime", "0"], "--arm-realtime: must be within 1..99, got 0"),
    ("ur=ur:sim", "--arm ur=ur:sim: TARGET 'sim' is the simulator that --sims starts; add --sims"),
    ("ur=ur:host?max_tracking=-1",
     "--arm ur=ur:host?max_tracking=-1: max_tracking: must be a positive number of m, got -1.0"),
])
def test_a_malformed_arm_is_named(value, message):
    flags = value if isinstance(value, list) else [value]
    res = subprocess.run([sys.executable, "-m", "dqpose.cli", "serve", "--arm", *flags],
                         capture_output=True, text=True, timeout=30, cwd=ROOT)
    assert (res.returncode, res.stderr) == (2, f"dqpose serve: error: {message}\n")


def test_a_misspelt_arm_key_is_named_with_the_nearest_one():
    res = subprocess.run([sys.executable, "-m", "dqpose.cli", "serve", "--arm",
                          "piper=piper:sim?max_trackin=0.003"], capture_output=True, text=True,
                         timeout=30, cwd=ROOT)
    assert res.returncode == 2
    assert res.stderr.startswith("dqpose serve: error: --arm piper=piper:sim?max_trackin=0.003: "
                                 "max_trackin: unknown arm key"), res.stderr
    assert "did you mean 'max_tracking'?" in res.stderr


def test_serve_help_lists_every_service_and_every_arm_key():
    from dqpose.drivers import ARM_KEYS
    from dqpose.rpc.server import SERVICERS
    res = subprocess.run([sys.executable, "-m", "dqpose.cli", "serve", "--help"],
                         capture_output=True, text=True, timeout=30, cwd=ROOT)
    assert res.returncode == 0
    text = " ".join(res.stdout.split())
    for servicer in SERVICERS:
        assert servicer.NAME in text
    for key in ARM_KEYS.values():
        assert " ".join(key.describe().split()) in text


def test_an_arm_given_twice_or_unreachable_is_named():
    res = subprocess.run([sys.executable, "-m", "dqpose.cli", "serve", "--arm", "a=ur:x",
                          "--arm", "a=ur:y"], capture_output=True, text=True, timeout=30, cwd=ROOT)
    assert (res.returncode, res.stderr) == (2, "dqpose serve: error: --arm: 'a' is given twice\n")
    pytest.importorskip("rtde_control")
    # nothing listens on 127.0.0.254's UR ports
    res = subprocess.run([sys.executable, "-m", "dqpose.cli", "serve", "--port", "0", "--arm",
                          "ur=ur:127.0.0.254"], capture_output=True, text=True, timeout=60,
                         cwd=ROOT)
    assert res.returncode == 2
    assert res.stderr.startswith("dqpose serve: error: --arm ur=ur:127.0.0.254: host: cannot "
                                 "reach a UR controller at 127.0.0.254"), res.stderr


@pytest.mark.parametrize("flags, loop", [([], "process"), (["--arm-loop", "thread"], "thread")],
                         ids=["auto", "thread"])
def test_serve_with_an_arm_executes_plans_on_it_and_stops_it_at_shutdown(flags, loop):
    pytest.importorskip("rtde_control")
    import math
    import signal

    import numpy as np

    from dqpose import dq, trajectory
    from dqpose.drivers.rotvec import pose_from_rotvec
    from dqpose.drivers.sim.ur import URSimProcess
    from dqpose.rpc.client import Client

    limits = trajectory.Limits(0.2, 1.0, 1.0, 2.0, 10.0, 20.0)
    home = np.array([0.4, -0.1, 0.3, math.pi, 0.0, 0.0])
    with URSimProcess() as sim:
        sim.set_pose(home)
        proc, events = serving("--arm", f"ur=ur:{sim.host}", *flags)
        try:
            arm = next(e for e in events if e.get("event") == "arm")
            assert (arm["name"], arm["spec"], arm["loop"]) == ("ur", f"ur:{sim.host}", loop)
            start = pose_from_rotvec(home)
            q, t = dq.to_pose(start)
            goal = dq.from_pose(q, t + [0.03, 0.0, 0.02])
            with Client(events[-1]["address"]) as c:
                states = [f.state for f in c.execute("ur", [start, goal], limits)]
            assert states[-1] == "FINISHED"
            proc.send_signal(signal.SIGTERM)
            assert proc.wait(timeout=30) == 0
            st = sim.state()
            assert not st["servoing"] and not st["moving"]
        finally:
            if proc.poll() is None:
                proc.kill()


def test_serve_records_every_stream_into_a_file_finished_at_sigterm(tmp_path):
    import signal

    from dqpose.record.reader import read
    from dqpose.rpc.client import Client
    from tests.record import _stream

    proc, events = serving("--record", str(tmp_path / "rec"), "--record-max-mb", "100")
    try:
        answers = list(Client(events[-1]["address"]).stream_fuse(
            _stream.batches(20), output_rate=_stream.RATE))
    finally:
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    (name,) = list((tmp_path / "rec").iterdir())
    rec = read(name)
    (call,) = rec.calls.values()
    assert call.rpc == "dqpose.v1.Fusion/StreamFuse" and call.code == "OK"
    assert sum(e.kind == "request" for e in rec.events) == 20
    assert sum(e.kind == "answer" for e in rec.events) == len(answers) > 0
    assert json.dumps({"event": "recording", "file": str(name)}) in err.splitlines()


@pytest.mark.parametrize("flags, message", [
    (["--record-max-mb", "0"], "--record-max-mb: must be > 0, got 0"),
    (["--record-max-s", "-1"], "--record-max-s: must be > 0, got -1"),
    (["--record-queue", "0"], "--record-queue: must be > 0, got 0"),
])
def test_a_recording_bound_out_of_range_is_named(tmp_path, flags, message):
    res = subprocess.run([sys.executable, "-m", "dqpose.cli", "serve", "--record",
                          str(tmp_path), *flags], capture_output=True, text=True, timeout=30,
                         cwd=ROOT)
    assert (res.returncode, res.stderr) == (2, f"dqpose serve: error: {message}\n")


def test_a_ctrl_c_to_the_servers_process_group_leaves_a_finished_recording(tmp_path):
    import os
    import signal

    from dqpose.record.reader import read
    from dqpose.rpc.client import Client
    from tests.record import _stream

    proc = subprocess.Popen([sys.executable, "-m", "dqpose.cli", "serve", "--port", "0",
                             "--record", str(tmp_path)], cwd=ROOT, stderr=subprocess.PIPE,
                            text=True, start_new_session=True)
    try:
        line = json.loads(proc.stderr.readline())
        answers = list(Client(line["address"]).stream_fuse(_stream.batches(10),
                                                           output_rate=_stream.RATE))
    finally:
        os.killpg(proc.pid, signal.SIGINT)      # what a terminal's Ctrl-C does
        _, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    (name,) = list(tmp_path.iterdir())
    rec = read(name)        # complete: footer, summary, every CRC
    assert sum(e.kind == "answer" for e in rec.events) == len(answers) > 0
    assert list(rec.calls.values())[0].code == "OK"


def test_replica_name_is_logged_and_answered():
    import grpc
    from grpc_health.v1 import health_pb2, health_pb2_grpc

    proc, events = serving("--replica-name", "east-2")
    try:
        assert events[-1]["replica"] == "east-2"
        with grpc.insecure_channel(events[-1]["address"]) as ch:
            _, call = health_pb2_grpc.HealthStub(ch).Check.with_call(
                health_pb2.HealthCheckRequest(), timeout=10)
        assert ("x-dqpose-replica", "east-2") in call.initial_metadata()
    finally:
        proc.kill()
        proc.wait(10)
