"""`dqpose world frames` against a real server on 127.0.0.1: the tree as text (parent -> child,
kind, rate, span, sources) and as JSON, and an unknown world's NOT_FOUND."""
from __future__ import annotations

import json

import numpy as np

from dqpose import dq
from dqpose.frames import Static
from dqpose.fusion import Source
from dqpose.rpc.client import Batch, Client
from tests.cli._cli import run
from tests.rpc._grpc_server import ServerThread

ONE = np.array([1.0, 0, 0, 0, 0, 0, 0, 0])


def test_world_frames_prints_the_tree_and_its_json(capsys):
    with ServerThread() as server:
        with Client(server.target, world="cell") as c:
            c.configure_world([Source("cam")], statics=[
                Static("box", "tip", ONE), Static("", "table", ONE),
                Static("tip", "tcp", dq.from_pose([1.0, 0, 0, 0], [0, 0, 0.1]))],
                static_bodies=["shelf"])
            times = np.arange(64) / 32          # 2 s at 32 Hz: exact binary times
            n = len(times)
            list(c.publish([Batch(np.tile(ONE, (n, 1)), np.tile(np.eye(6) * 1e-6, (n, 1, 1)),
                                  None, ["cam"] * n, ["box"] * n, times)]))
        args = ["world", "frames", "--server", server.target, "--world", "cell"]
        code, out, err = run(capsys, *args)
        assert code == 0, err
        assert out.splitlines() == [
            "world",
            "world -> box: body; 33 Hz; 1.969 s kept; newest 1.969 s; sources cam",
            "  box -> tip: static",
            "    tip -> tcp: static",
            "world -> shelf: static body",
            "world -> cam: source",
            "world -> table: static"]
        code, out, err = run(capsys, *args, "--json")
        assert code == 0, err
        got = {f["name"]: f for f in json.loads(out)}
        assert got["box"] == {"name": "box", "parent": "", "kind": "body", "oldest": 0.0,
                              "newest": 1.96875, "rate_hz": 33.0, "sources": ["cam"]}
        assert (got["tcp"]["kind"], got["tcp"]["parent"]) == ("static", "tip")
        assert got[""]["kind"] == "world"
        code, out, err = run(capsys, "world", "frames", "--server", server.target, "--world",
                             "elsewhere")
        assert code != 0 and "NOT_FOUND" in err and "elsewhere" in err, err
