"""dqpose.rpc.replay of a server's rotated recording as one sequence: a real server records a
StreamFuse stream, a Fuse and a World (configured, published to by two named worlds' producers,
subscribed) into files a few kB each, so that the stream, the world's producers and the
subscriptions go on across the files; the run replays whole, in process and into a server, to
every answer byte for byte; one answer changed in the second file is reported in that file at
its time; one file alone skips the calls that began before it."""
from __future__ import annotations

import os
import shutil
import threading

import grpc
import numpy as np
import pytest

from dqpose.record.reader import read, read_all, runs
from dqpose.record.recorder import Recorder
from dqpose.rpc import replay, replay_world
from dqpose.rpc._proto.dqpose.v1 import fusion_pb2 as pb
from dqpose.rpc.client import Client
from dqpose.rpc.fusion import STREAM_FUSE
from dqpose.rpc.server import ServerConfig
from tests._polling import wait_until
from tests.record import _stream
from tests.rpc._grpc_server import ServerThread
from tests.rpc.test_record import stream_bytes
from tests.rpc.test_world_service import SOURCES, TWIST, Collector, measurements

pytest.importorskip("foxglove", reason="the [record] extra")

WORLDS = ("", "cell-b")
BATCHES, PER = 40, 3


def _cells(server):
    (w,) = [s for s in server.running.servicers if s.NAME == replay_world.NAME]
    return [w.hub(n, make=True) for n in WORLDS]


def _publish(target: str, world: str, k: int) -> None:
    batches = [measurements("cam1", 0.01 * (j * PER + np.arange(PER)), 100 * k + j,
                            body="box" if j % 2 else "cup") for j in range(BATCHES)]
    with Client(target, world=world or None) as c:
        assert len(list(c.publish(batches, producer="cam1"))) == BATCHES


@pytest.fixture(scope="module")
def rotated(tmp_path_factory):
    folder = tmp_path_factory.mktemp("rotated")
    # 64 kB files: the stream's 400 requests and the worlds' 80 span several of them
    recorder = Recorder(folder, max_bytes=64_000)
    with ServerThread(ServerConfig(port=0, recorder=recorder)) as s:
        subs = []
        for name in WORLDS:
            with Client(s.target, world=name or None) as c:
                c.configure_world(SOURCES, twist_covariance=TWIST, window=10.0)
            subs.append(Collector(s.target, world=name or None, rate_hz=20.0))
        # each world's subscriber and the recorder's own
        assert wait_until(lambda: all(len(c.subscriptions) == 2 for c in _cells(s)), timeout=10)
        stream = threading.Thread(target=stream_bytes, args=(s.target, _stream.requests(400)))
        stream.start()
        for k, name in enumerate(WORLDS):
            _publish(s.target, name, k)
        stream.join(60)
        Client(s.target).fuse(np.array([[1.0, 0, 0, 0, 0, 0.1, 0, 0]] * 2), weights=[1.0, 2.0])
        assert wait_until(lambda: all(len(x.answers) > 5 for x in subs), timeout=10)
        for x in subs:
            x.stop()
        assert wait_until(lambda: all(len(c.subscriptions) == 1 for c in _cells(s)), timeout=10)
    recorder.close()
    assert recorder.dropped == 0
    return folder, recorder.files, [len(x.answers) for x in subs]


def test_the_files_are_one_run_in_order_and_calls_go_on_across_them(rotated):
    folder, files, _ = rotated
    assert len(files) >= 4
    assert runs([folder]) == [files]
    assert runs([os.path.join(folder, "*.mcap")]) == [files]
    assert runs(reversed(files)) == [files]
    whole = read_all(files)
    spanning = {c.rpc for c in whole.calls.values()
                if len({e.file for e in whole.events if e.call == c.id}) > 1}
    assert {STREAM_FUSE, replay_world.PUBLISH, replay_world.SUBSCRIBE} <= spanning
    assert not any(c.continued for c in whole.calls.values())


def test_the_run_replays_whole_in_process_to_every_answer(rotated):
    folder, files, subscribed = rotated
    whole = read_all(files)
    report = replay.replay(runs([folder]), replay.InProcess())
    assert report.difference is None, str(report.difference)
    assert report.cut is None and report.skipped == []
    assert (report.files, report.runs) == (len(files), 1)
    # 2 Configure, 2 Subscribe and the recorder's own 2, 2 Publish, StreamFuse, Fuse
    assert report.calls == len(whole.calls) == 10
    assert report.requests == 2 + 4 + 2 * BATCHES + 400 + 1
    recorded = sum(e.kind == "answer" for e in whole.events)
    assert report.answers >= recorded >= 2 + 2 * BATCHES + sum(subscribed) + 20


def test_the_run_replays_whole_into_a_server(rotated):
    folder, files, _ = rotated
    with ServerThread() as s, grpc.insecure_channel(s.target) as ch:
        report = replay.replay(runs([folder]), replay.Remote(ch))
    assert report.difference is None, str(report.difference)
    assert report.calls == 10 and report.skipped == []


def test_one_file_alone_skips_the_calls_that_began_before_it(rotated):
    _, files, _ = rotated
    report = replay.replay(read(files[1]), replay.InProcess())
    assert report.difference is None
    assert any(STREAM_FUSE in line and "began before" in line for line in report.skipped)


def _rewrite(src: str, dst: str, change) -> None:
    """A copy of MCAP file ``src`` at ``dst`` with each message's data ``change(channel,
    message)`` (mcap's own writer)."""
    from mcap.reader import make_reader
    from mcap.writer import Writer

    with open(src, "rb") as f, open(dst, "wb") as out:
        reader = make_reader(f)
        header = reader.get_header()
        w = Writer(out)
        w.start(profile=header.profile, library=header.library)
        schemas: dict[int, int] = {}
        channels: dict[int, int] = {}
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            if schema is not None and schema.id not in schemas:
                schemas[schema.id] = w.register_schema(schema.name, schema.encoding, schema.data)
            if channel.id not in channels:
                channels[channel.id] = w.register_channel(
                    channel.topic, channel.message_encoding,
                    schemas.get(channel.schema_id, 0), channel.metadata)
            w.add_message(channels[channel.id], message.log_time, change(channel, message),
                          message.publish_time, message.sequence)
        w.finish()


def test_an_answer_changed_in_the_second_file_is_reported_there(rotated, tmp_path):
    _, files, _ = rotated
    whole = read_all(files)
    (stream,) = [c for c in whole.calls.values() if c.rpc == STREAM_FUSE]
    answers = [e for e in whole.events if e.call == stream.id and e.kind == "answer"]
    k = next(i for i, e in enumerate(answers) if e.file == 1)   # its first answer in file 2
    changed = pb.FusedPose.FromString(answers[k].data)
    changed.covariance[7] = np.nextafter(changed.covariance[7], 1.0)     # one ulp
    copies = [str(tmp_path / os.path.basename(f)) for f in files]
    for f, c in zip(files, copies):
        shutil.copy(f, c)
    os.remove(copies[1])
    _rewrite(files[1], copies[1], lambda ch, m: changed.SerializeToString()
             if m.log_time == answers[k].ns and ch.topic.endswith("/answers")
             and ch.metadata.get("call") == str(stream.id) else m.data)
    report = replay.replay(runs([tmp_path]), replay.InProcess())
    d = report.difference
    assert d is not None and (d.call.id, d.answer) == (stream.id, k)
    assert (d.file, d.ns) == (copies[1], answers[k].ns)
    assert "covariance[7] recorded" in d.what
    assert f"(recorded in {os.path.basename(files[1])} at {answers[k].ns / 1e9:.6f} s" \
        in str(d)


def test_a_run_whose_last_file_was_cut_short_replays_up_to_the_cut(rotated, tmp_path):
    # the server killed while it wrote a file of the stream: its last file, without a summary
    # or a footer, cut in a chunk
    _, files, _ = rotated
    whole = read_all(files)
    (stream,) = [c for c in whole.calls.values() if c.rpc == STREAM_FUSE]
    # a file in the middle of the stream: its second half holds some of its requests
    held = sorted(e.file for e in whole.events if e.call == stream.id and e.kind == "request")
    k = held[len(held) // 2]
    for f in files[:k + 1]:
        shutil.copy(f, tmp_path / os.path.basename(f))
    last = tmp_path / os.path.basename(files[k])
    last.write_bytes(last.read_bytes()[:last.stat().st_size // 2])
    report = replay.replay(runs([tmp_path]), replay.InProcess())
    assert report.difference is None, str(report.difference)
    assert report.cut is not None and report.cut.startswith("not replayable after ")
    assert f"{last}: not a complete MCAP recording" in report.cut
    requests = sum(e.kind == "request" for e in whole.events if e.file < k)
    assert requests <= report.requests < len([e for e in whole.events if e.kind == "request"])
    # every call begun before the cut file is replayed, none begun after it (where the Fuse
    # falls among the files depends on the recording's timing)
    before = {e.call for e in whole.events if e.file < k}
    upto = {e.call for e in whole.events if e.file <= k}
    assert report.files == k + 1 and len(before) <= report.calls <= len(upto)
    # a file of which nothing can be read: a cut with nothing replayed; one that is not MCAP
    # is refused
    last.write_bytes(last.read_bytes()[:100])
    report = replay.replay(runs([last]), replay.InProcess())
    assert report.calls == 0 and len(report.cuts) == 1
    assert report.cut.startswith(f"not replayable at all: {last}: not a complete MCAP recording")
    last.write_bytes(b"PK\x03\x04" + last.read_bytes()[4:])
    with pytest.raises(ValueError, match="not an MCAP file"):
        replay.replay(runs([last]), replay.InProcess())
