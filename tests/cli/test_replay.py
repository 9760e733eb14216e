"""``dqpose replay``: exit 0 when a recording replays to every answer, 1 with the first
difference, 2 naming a file that is not a recording or a bad --speed; a file cut short or with a
byte flipped (alone, or in a directory beside a whole one) replays up to where it can be read,
says where and why it stopped and exits 2, never "identical"."""
from __future__ import annotations

import re
import subprocess
import sys

import pytest

from dqpose.record.reader import read
from tests.cli._cli import ROOT, serving
from tests.record import _stream
from tests.rpc.test_replay import record_run


def dqpose(*argv):
    return subprocess.run([sys.executable, "-m", "dqpose.cli", "replay", *argv],
                          capture_output=True, text=True, timeout=120, cwd=ROOT)


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("rec")
    a = record_run(d / "a", _stream.requests(30))
    b = record_run(d / "b", _stream.requests(30, window=0.05))
    return a.path, b.path


def test_replay_in_process_and_at_recorded_speed_finds_every_answer_identical(files):
    rec = read(files[0])
    answers = sum(e.kind == "answer" for e in rec.events)
    for flags in ([], ["--speed", "1"]):
        res = dqpose(files[0], *flags)
        assert res.returncode == 0, res.stderr
        lines = res.stdout.splitlines()
        assert lines[0].startswith(f"replayed 4 calls, 33 requests, {answers} answers in ")
        assert lines[-1] == "every answer identical"


def test_replay_against_a_server(files):
    proc, events = serving()
    try:
        res = dqpose(files[0], "--server", events[-1]["address"])
    finally:
        proc.terminate()
        proc.communicate(timeout=30)
    assert res.returncode == 0, res.stderr
    assert res.stdout.splitlines()[-1] == "every answer identical"


def test_compare_names_the_first_difference(files):
    res = dqpose(files[0], "--compare", files[1])
    assert res.returncode == 1
    assert res.stdout.splitlines()[-1] == (
        f"first difference: call 1 (dqpose.v1.Fusion/StreamFuse), its status: not the same "
        f"requests: {files[1]} call 1 (dqpose.v1.Fusion/StreamFuse) was sent others")
    same = dqpose(files[0], "--compare", files[0])
    assert same.returncode == 0 and same.stdout.splitlines()[-1] == "every answer identical"


def test_what_cannot_be_replayed_is_named(tmp_path, files):
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not mcap at all")
    res = dqpose(str(junk))
    assert res.returncode == 2
    assert res.stderr.startswith(f"dqpose replay: error: {junk}: not an MCAP file")
    res = dqpose(str(tmp_path / "missing.mcap"))
    assert (res.returncode, res.stderr) == (
        2, f"dqpose replay: error: {tmp_path / 'missing.mcap'}: No such file or directory\n")
    res = dqpose(files[0], "--speed", "0")
    assert (res.returncode, res.stderr) == (
        2, "dqpose replay: error: --speed: 'max' or a number > 0, got '0'\n")


def test_a_rotated_recording_replays_as_one_run_from_its_directory(tmp_path):
    from dqpose.record.recorder import Recorder
    from dqpose.rpc.server import ServerConfig
    from tests.rpc._grpc_server import ServerThread
    from tests.rpc.test_record import stream_bytes

    recorder = Recorder(tmp_path / "run", max_bytes=16_000)
    with ServerThread(ServerConfig(port=0, recorder=recorder)) as s:
        answers = len(stream_bytes(s.target, _stream.requests(300)))
    recorder.close()
    n = len(recorder.files)
    assert n >= 3
    res = dqpose(str(tmp_path / "run"))
    assert res.returncode == 0, res.stderr
    lines = res.stdout.splitlines()
    assert lines[0].startswith(f"replayed 1 calls, 300 requests, {answers} answers from {n} "
                               f"files in 1 run in ")
    assert lines[-1] == "every answer identical" and res.stderr == ""
    # each file alone (before: all a replay could take) skips the stream after the first
    alone = dqpose(recorder.files[1])
    assert "began before" in alone.stderr and alone.stdout.startswith("replayed 0 calls")
    same = dqpose(str(tmp_path / "run" / "*.mcap"), "--compare", str(tmp_path / "run"))
    assert same.returncode == 0 and same.stdout.splitlines()[-1] == "every answer identical"


def _flipped(whole: bytes) -> bytes:
    data = bytearray(whole)
    data[len(whole) // 3] ^= 0x10          # a CRC failure
    return bytes(data)


#: the probe's four damaged copies of a recording
DAMAGES = {"cut at 50 %": lambda whole: whole[:len(whole) // 2],
           "cut at 90 %": lambda whole: whole[:len(whole) * 9 // 10],
           "missing its last 10 bytes": lambda whole: whole[:-10],
           "a byte flipped": _flipped}


def _counts(stdout: str) -> tuple[int, int]:
    m = re.match(r"replayed (\d+) calls, (\d+) requests, ", stdout)
    assert m, stdout
    return int(m[1]), int(m[2])


@pytest.mark.parametrize("damage", list(DAMAGES))
def test_a_damaged_file_replays_what_it_can_says_where_it_stopped_and_exits_2(files, tmp_path,
                                                                             damage):
    with open(files[0], "rb") as f:
        whole = f.read()
    path = tmp_path / "damaged.mcap"
    path.write_bytes(DAMAGES[damage](whole))
    res = dqpose(str(path))
    assert res.returncode == 2, (res.stdout, res.stderr)
    assert "identical" not in res.stdout + res.stderr
    lines = res.stdout.splitlines()
    (cut,) = [line for line in lines if line.startswith("not replayable ")]
    assert f": {path}: not a complete MCAP recording: byte " in cut, cut
    assert lines[-1].startswith("no difference up to where it stopped") or \
        lines[-1] == "nothing replayed"
    calls, requests = _counts(res.stdout)
    assert requests <= 30 + 3
    if damage != "a byte flipped":
        assert requests > 0         # the readable part was replayed


def test_a_directory_with_a_cut_file_replays_every_run_and_exits_2(files, tmp_path):
    with open(files[0], "rb") as f:
        whole = f.read()
    (tmp_path / "a.mcap").write_bytes(whole[:len(whole) // 2])
    (tmp_path / "b.mcap").write_bytes(whole)
    res = dqpose(str(tmp_path))
    assert res.returncode == 2, (res.stdout, res.stderr)
    assert "identical" not in res.stdout
    assert " from 2 files in 2 runs in " in res.stdout.splitlines()[0]
    (cut,) = [line for line in res.stdout.splitlines() if line.startswith("not replayable ")]
    assert f"{tmp_path / 'a.mcap'}: not a complete MCAP recording" in cut
    calls, requests = _counts(res.stdout)
    assert calls > 4 and requests > 33      # b.mcap whole after the part of a.mcap
