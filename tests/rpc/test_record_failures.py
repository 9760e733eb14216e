"""Recording failures are seen (issue 36, P6): ``serve --record`` refuses a directory it cannot
write; a disk that fills while a server records (a small tmpfs) is logged once with its cause,
counted on the metrics port, said by the health service ``dqpose.record`` (the server's own ""
stays SERVING), and marked in the next file once the disk has room again, read back by mcap's
own reader. The file systems are real mounts (root: ``chmod`` does not stop it)."""
from __future__ import annotations

import contextlib
import json
import os
import re
import subprocess
import sys
import urllib.request

import numpy as np
import pytest
from mcap.reader import make_reader

from dqpose import dq
from dqpose.record import HEALTH_SERVICE
from dqpose.record.recorder import Recorder
from dqpose.record.topics import DROPPED_TOPIC
from dqpose.rpc.client import Client
from dqpose.rpc.server import ServerConfig
from tests._polling import wait_until
from tests.cli._cli import ROOT
from tests.rpc._grpc_server import ServerThread
from tests.rpc.server._blending import socket_free_port


@contextlib.contextmanager
def tmpfs(path, size: str, *options: str):
    """A tmpfs of ``size`` mounted on ``path`` (skipped where this user cannot mount one)."""
    os.makedirs(path, exist_ok=True)
    res = subprocess.run(["mount", "-t", "tmpfs", "-o", ",".join((f"size={size}", *options)),
                          "tmpfs", str(path)], capture_output=True, text=True)
    if res.returncode:
        pytest.skip(f"cannot mount a tmpfs here: {res.stderr.strip()}")
    try:
        yield path
    finally:
        subprocess.run(["umount", "-l", str(path)], check=True)


def serve_record(directory) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "dqpose.cli", "serve", "--port", "0",
                           "--record", str(directory)], capture_output=True, text=True,
                          timeout=60, cwd=ROOT)


def test_serve_refuses_a_read_only_directory_in_one_line(tmp_path):
    with tmpfs(tmp_path / "ro", "1m", "ro") as ro:
        res = serve_record(ro / "runs")      # its parent read-only: cannot be made
        assert (res.returncode, res.stderr) == (
            2, f"dqpose serve: error: --record {ro}/runs: Read-only file system\n")
    with tmpfs(tmp_path / "ro", "1m") as d:
        (d / "runs").mkdir()
        subprocess.run(["mount", "-o", "remount,ro", str(d)], check=True)
        res = serve_record(d / "runs")      # there, but read-only
        assert (res.returncode, res.stderr) == (
            2, f"dqpose serve: error: --record {d}/runs: cannot write into it: Read-only file "
               f"system\n")
        assert os.listdir(d / "runs") == []


def test_serve_refuses_a_directory_under_a_file(tmp_path):
    (tmp_path / "file").write_text("x")
    res = serve_record(tmp_path / "file" / "runs")
    assert (res.returncode, res.stderr) == (
        2, f"dqpose serve: error: --record {tmp_path}/file/runs: Not a directory\n")


def fuse_until(client: Client, done, rng, most: int = 400) -> int:
    """Fuse calls of 50 random poses (little to compress) until ``done()``; how many."""
    for n in range(1, most + 1):
        poses = dq.normalize(rng.normal(size=(50, 8)))
        client.fuse(poses, weights=np.ones(50))
        if done():
            return n
    raise AssertionError(f"not done after {most} calls")


def failed_metric(port: int) -> float:
    text = urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=10).read()
    m = re.search(r'dqpose_record_messages_total\{outcome="failed"\} (\S+)', text.decode())
    assert m, text
    return float(m.group(1))


def test_a_full_disk_is_logged_counted_and_said_by_health_then_marked(tmp_path, caplog):
    rng = np.random.default_rng(7)
    with tmpfs(tmp_path / "disk", "120k") as disk:
        filler = disk / "filler"
        filler.write_bytes(bytes(64 << 10))     # ~56 kB left for the recording
        runs = disk / "runs"
        recorder = Recorder(runs)
        with socket_free_port() as port, \
                ServerThread(ServerConfig(port=0, recorder=recorder, metrics_port=port)) as s, \
                Client(s.target) as c:
            assert c.health(HEALTH_SERVICE) == "SERVING"
            fuse_until(c, lambda: c.health(HEALTH_SERVICE) == "NOT_SERVING", rng)
            assert c.health("") == "SERVING"    # a full disk does not take the replica out
            fuse_until(c, lambda: recorder.failed >= 20, rng)
            assert wait_until(lambda: failed_metric(port) == recorder.failed > 0, 10)
            (line,) = [json.loads(r.getMessage()) for r in caplog.records
                       if '"recording_failed"' in r.getMessage()]
            assert line["error"] == "No space left on device (ENOSPC)"
            assert line["file"] == recorder.files[0]
            filler.unlink()                    # room again: a new file, behind a marker
            assert wait_until(lambda: c.health(HEALTH_SERVICE) == "SERVING", 30, 0.05)
            assert len(recorder.files) == 2
            c.fuse(dq.normalize(rng.normal(size=(3, 8))), weights=np.ones(3))
        lost = recorder.failed      # the server stopped: the writer's last count
        assert [json.loads(r.getMessage())["event"] for r in caplog.records
                if r.name == "dqpose.record" and r.levelname == "ERROR"] == ["recording_failed"]
        with open(recorder.files[1], "rb") as f:
            got = [(c.topic, json.loads(m.data) if c.topic == DROPPED_TOPIC else None)
                   for _, c, m in make_reader(f).iter_messages(log_time_order=False)]
        topic, marker = got[0]
        assert topic == DROPPED_TOPIC
        assert (marker["count"], marker["error"]) == (lost, "No space left on device (ENOSPC)")
        assert marker["first_dropped"] < marker["resumed"]
        assert any(t == "/dqpose/dqpose.v1.Fusion/Fuse/requests" for t, _ in got[1:])
