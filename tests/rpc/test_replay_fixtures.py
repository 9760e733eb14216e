"""The recordings of tests/fixtures/recordings/ (made by its make.py with a real ``dqpose serve
--record``) replay through ``dqpose replay`` to every answer, byte for byte: StreamFuse at
output_rate 20 Hz and 0, robust off and on, with a latency-estimating source; a World with two
producers and subscribers at 20 Hz and 0. The world's Lookups, which a server does not record,
are asked of a server the world's recording was replayed into and give the recorded bytes."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import grpc
import pytest

from tests.cli._cli import ROOT, serving

pytest.importorskip("foxglove", reason="the [record] extra")

FIXTURES = Path(ROOT) / "tests" / "fixtures" / "recordings"
STREAM_FUSE = sorted(FIXTURES.glob("streamfuse-*.mcap"))


def replay(path: Path, *flags: str) -> list[str]:
    res = subprocess.run([sys.executable, "-m", "dqpose.cli", "replay", str(path), *flags],
                         capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert res.returncode == 0, res.stdout + res.stderr
    lines = res.stdout.splitlines()
    assert lines[-1] == "every answer identical" and res.stderr == "", res.stdout + res.stderr
    return lines


def test_the_set_is_there_and_small():
    names = {p.name for p in FIXTURES.glob("*.mcap")}
    assert names == {"world.mcap"} | {f"streamfuse-rate{r}-robust-{o}.mcap"
                                      for r in ("20", "0") for o in ("on", "off")}
    assert all(p.stat().st_size < 100_000 for p in FIXTURES.glob("*.mcap"))


@pytest.mark.parametrize("path", STREAM_FUSE, ids=lambda p: p.stem)
def test_a_stream_fuse_recording_replays_to_every_answer(path):
    (first, *_) = replay(path)
    assert first.startswith("replayed 1 calls, 24 requests, "), first


def test_the_world_recording_replays_in_process_and_into_a_server_to_the_same_lookups():
    (first, *_) = replay(FIXTURES / "world.mcap")
    # Configure, two producers' Publish streams, two subscribers and the recorder's own
    assert first.startswith("replayed 6 calls, 28 requests, "), first
    lookups = json.loads((FIXTURES / "world_lookups.json").read_text())
    proc, events = serving()
    try:
        target = events[-1]["address"]
        replay(FIXTURES / "world.mcap", "--server", target)
        with grpc.insecure_channel(target) as ch:
            call = ch.unary_unary("/dqpose.v1.World/Lookup")
            got = [call(bytes.fromhex(x["request"]), timeout=30).hex() for x in lookups]
    finally:
        proc.terminate()
        proc.communicate(timeout=30)
    assert len(got) == 3 and got == [x["answer"] for x in lookups]
