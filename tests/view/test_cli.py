"""The ``dqpose view`` command, run as a user runs it: a folder of recordings shows its newest
run (as ``replay`` takes a folder); ``--token-file`` reaches a token-protected server (``--server``,
and ``--live`` as its ``?token=``), keeps the page on the loopback, and is refused where it means
nothing."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import threading

import pytest

from tests.cli._cli import ROOT

pytest.importorskip("viser", reason="the [view] extra (pip install -e '.[view]')")
pytest.importorskip("foxglove", reason="the [record] extra")

TOKEN = "s3cret-token"


def _dqpose_view(*args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "dqpose.cli", "view", *args, "--port", "0"],
                            cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            text=True)


def _until_event(proc: subprocess.Popen, name: str) -> tuple[dict, list[str]]:
    """The first event ``name`` the view says, and the lines it said before."""
    said = []
    for line in proc.stderr:
        if line.startswith("{") and json.loads(line)["event"] == name:
            return json.loads(line), said
        said.append(line)
    raise AssertionError(f"dqpose view ended before {name!r}: {''.join(said)}")


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "dqpose.cli", "view", *args, "--port", "0"],
                          capture_output=True, text=True, timeout=120, cwd=ROOT)


def test_a_folder_shows_its_newest_run(tmp_path):
    from tests.view._cell import record_cell
    from tests.view.test_page import record

    runs = tmp_path / "runs"
    runs.mkdir()
    # two servers' runs, named as a server names them (its start, then the file's number)
    shutil.move(record(tmp_path / "a"), runs / "dqpose-20250101T000000Z-0000.mcap")
    newest = runs / "dqpose-20250102T000000Z-0000.mcap"
    shutil.move(record_cell(tmp_path / "b"), newest)
    for arg in (str(runs), str(runs / "*.mcap")):
        proc = _dqpose_view(arg)
        try:
            info, before = _until_event(proc, "viewing")
        finally:
            proc.terminate()
            proc.wait(30)
        assert info["files"] == [os.path.normpath(newest)]
        assert info["arms"] == ["piper", "ur"]          # the cell's, not the first run's
        assert before == [f"dqpose view: {arg} holds 2 runs; showing the last by name "
                          f"({newest.name}, 1 file); name a file to see another\n"]
    empty = tmp_path / "empty"
    empty.mkdir()
    res = _run(str(empty))
    assert (res.returncode, res.stderr) == (2, f"dqpose view: error: {empty}: no .mcap file "
                                               f"there\n")


def test_the_token_file_is_refused_where_it_protects_nothing(tmp_path):
    token = tmp_path / "token"
    token.write_text(TOKEN + "\n")
    res = _run("--server", "127.0.0.1:1", "--token-file", str(token), "--host", "0.0.0.0")
    assert res.returncode == 2
    assert res.stderr.startswith("dqpose view: error: --host 0.0.0.0: the page has no "
                                 "authentication, so with --token-file it serves the loopback "
                                 "only")
    res = _run(str(tmp_path / "x.mcap"), "--token-file", str(token))
    assert (res.returncode, res.stderr) == (
        2, "dqpose view: error: --token-file: only with --server or --live (a file needs "
           "none)\n")
    res = _run("--server", "127.0.0.1:1", "--token-file", str(tmp_path / "missing"))
    assert (res.returncode, res.stderr) == (
        2, f"dqpose view: error: --token-file {tmp_path / 'missing'}: No such file or "
           f"directory\n")


def test_a_server_that_needs_a_token_gets_it(tmp_path):
    from dqpose.rpc.server import ServerConfig
    from tests.rpc._grpc_server import ServerThread

    token = tmp_path / "token"
    token.write_text(TOKEN + "\n")
    with ServerThread(ServerConfig(port=0, token=TOKEN)) as s:
        res = _run("--server", s.target)
        assert res.returncode == 2
        assert "authorization: missing bearer token" in res.stderr.splitlines()[-1]
        proc = _dqpose_view("--server", s.target, "--token-file", str(token))
        try:
            info, _ = _until_event(proc, "following")
        finally:
            proc.terminate()
            proc.wait(30)
        assert info["server"] == s.target


def test_live_takes_the_token_in_its_url(tmp_path):
    """``--live``: the token as ``serve --live`` takes it, ``?token=`` (a WebSocket server
    here stands for it and records the URL asked for)."""
    from websockets.sync.server import serve

    token = tmp_path / "token"
    token.write_text("a b&c\n")
    asked: list[str] = []

    def handler(ws) -> None:
        asked.append(ws.request.path)
        ws.close()

    with serve(handler, "127.0.0.1", 0) as server:
        threading.Thread(target=server.serve_forever, daemon=True).start()
        port = server.socket.getsockname()[1]
        res = _run("--live", f"127.0.0.1:{port}", "--token-file", str(token))
        server.shutdown()
    assert res.returncode == 2
    assert asked == ["/?token=a+b%26c"]
