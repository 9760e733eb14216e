"""dqpose.record.mcapread, the checked reading every reader of a recording goes through: files
built byte by byte (``_mcap.py``) read as ``mcap``'s own reader reads them; a chunk declaring
1 GiB refused before decompressing (``replay``, ``export``, ``view``); chunks holding more than
they declare, attachments and metadata declaring more than their record, records beyond the
file or over 64 MiB, statistics that miscount, failing CRCs, each named; and a real recording
with bytes flipped: every reader stops with a :class:`Damaged` (a replay with a cut), never
passes it, never raises anything else."""
from __future__ import annotations

import importlib.util
import struct
import subprocess
import sys
import zlib

import lz4.frame
import pytest
from mcap.opcode import Opcode
from mcap.records import Channel, Message
from mcap.stream_reader import StreamReader

from dqpose.record.mcapread import MAX_RATIO, MAX_RECORD_BYTES, Damaged, NotMcap, messages
from dqpose.record.reader import read, runs
from dqpose.record.recorder import Recorder
from dqpose.rpc import replay
from tests.cli._cli import ROOT
from tests.record import _stream
from tests.record._mcap import (
    DATA_START,
    attachment,
    channel,
    chunk,
    mcap,
    message,
    metadata,
    record,
    schema,
    statistics,
    zeros_zstd,
)
from tests.record.test_recorder import record_stream

GIB = 1 << 30


def _file(tmp_path, data: bytes, name: str = "f.mcap"):
    path = tmp_path / name
    path.write_bytes(data)
    return path


def test_chunks_of_each_compression_read_as_mcaps_own_reader_reads_them(tmp_path):
    meta = {"call": "7"}
    defs = schema() + channel(metadata=meta)
    path = _file(tmp_path, mcap(
        [chunk(defs + message(ns=1, data=b'{"a": 1}'), "zstd"), chunk(message(ns=2), "lz4"),
         chunk(message(ns=3), ""), message(ns=4), attachment(b"abc"), metadata({"k": "v"})],
        [schema(), channel(metadata=meta),
         statistics(4, {1: 4}, chunks=3, attachments=1, metadata=1)]))
    schemas: dict = {}
    mine = list(messages(path, schemas))
    channels, theirs = {}, []
    with open(path, "rb") as f:
        for r in StreamReader(f, validate_crcs=True).records:
            if isinstance(r, Channel):
                channels[r.id] = r
            elif isinstance(r, Message):
                c = channels[r.channel_id]
                theirs.append((c.topic, c.metadata, r.log_time, r.data))
    assert mine == theirs and [m[2] for m in mine] == [1, 2, 3, 4]
    assert schemas == {}        # protobuf schemas only
    assert mine[0][:2] == ("/t", meta)


@pytest.fixture(scope="module")
def bomb(tmp_path_factory):
    """The probe's file: one zstd chunk declaring 1 GiB, which its ~32 kB of zstd hold (zeros;
    its CRC 0, "not available", so a reader that decompresses then parses the GiB)."""
    return _file(tmp_path_factory.mktemp("bomb"), mcap(
        [chunk(b"", size=GIB, packed=zeros_zstd(GIB), crc=0)]), "bomb.mcap")


def test_a_chunk_declaring_a_gib_is_refused_by_every_reader_before_decompressing(bomb,
                                                                                  tmp_path):
    said = (f"{bomb}: not a complete MCAP recording: byte {DATA_START}: chunk record: it "
            f"declares {GIB} bytes uncompressed, more than the 64 MiB a chunk may hold: not "
            f"decompressed")
    with pytest.raises(Damaged) as e:
        list(messages(bomb))
    assert str(e.value) == said
    commands = [["replay", str(bomb)], ["export", str(bomb), "--ros2", str(tmp_path / "bag")]]
    if importlib.util.find_spec("viser"):       # the [view] extra
        commands.append(["view", str(bomb), "--port", "0"])
    for argv in commands:
        res = subprocess.run([sys.executable, "-m", "dqpose.cli", *argv], capture_output=True,
                             text=True, timeout=120, cwd=ROOT)
        assert res.returncode == 2, (argv, res.stdout, res.stderr)
        assert said in res.stdout + res.stderr, (argv, res.stdout, res.stderr)
        assert "identical" not in res.stdout
    assert not (tmp_path / "bag").exists()


def test_a_chunk_expanding_beyond_the_ratio_is_refused_before_decompressing(tmp_path):
    # 32 MiB of zeros, under the 64 MiB a chunk may hold, from a few kB of zstd (lz4 expands
    # ~255:1 at most): a file of many such chunks would cost gigabytes of decompression; its
    # CRC holds, so only the ratio stops it
    n, compression = 32 << 20, "zstd"
    packed = zeros_zstd(n)
    assert n > MAX_RATIO * len(packed)
    path = _file(tmp_path, mcap([chunk(b"", compression, size=n, packed=packed,
                                       crc=zlib.crc32(bytes(n)))] * 3))
    with pytest.raises(Damaged, match=rf"byte {DATA_START}: chunk record: it declares {n} "
                                      rf"bytes uncompressed from {len(packed)} compressed, "
                                      rf"more than the {MAX_RATIO}:1 a chunk may expand"):
        list(messages(path))


@pytest.mark.parametrize("compression", ["zstd", "lz4"])
def test_a_chunk_holding_more_than_it_declares_is_decompressed_one_byte_past_it(tmp_path,
                                                                                compression):
    # 64 MiB of zeros in a chunk declaring 1 MiB: zstd's frame states its content size, which
    # zstandard.decompress believes over the bound it is given; lz4 has no bound at all
    n = 64 << 20
    packed = zeros_zstd(n) if compression == "zstd" else lz4.frame.compress(bytes(n))
    path = _file(tmp_path, mcap([chunk(b"", compression, size=1 << 20, packed=packed, crc=0)]))
    with pytest.raises(Damaged, match=rf"byte {DATA_START}: chunk record: it holds more than "
                                      r"the 1048576 bytes it declares$"):
        list(messages(path))


@pytest.mark.parametrize("records, reason", [
    ([attachment(b"abc", declared=1 << 40)],
     "attachment record: its data declares 1099511627776 bytes where 7 are left in the "
     "attachment record"),
    ([metadata({"k": "v"}, declared=1 << 31)],
     "metadata record: its metadata declares 2147483648 bytes where 10 are left in the "
     "metadata record"),
    ([attachment(b"abc", crc=1)], "attachment record: its CRC fails"),
    ([record(Opcode.ATTACHMENT, b"", length=MAX_RECORD_BYTES + 1)],
     f"this attachment record declares {MAX_RECORD_BYTES + 1} bytes, more than the 64 MiB a "
     f"record may have"),
    ([record(Opcode.ATTACHMENT, bytes(100), length=1 << 20)],
     "the file ends 150 bytes into this attachment record of 1048576 bytes (cut short)"),
    ([chunk(message(), crc=1)], "chunk record: its CRC fails (recorded 0x00000001, computed "),
    ([schema(), channel(), chunk(message(cid=2))],
     "chunk record: its channel 2 was not defined before it"),
    ([chunk(record(Opcode.STATISTICS, b""))], "chunk record: its byte 0: statistics record of "
                                              "0 bytes (a chunk holds schemas, channels and "
                                              "messages"),
    ([schema(), channel(sid=3)], "channel record: channel 1's schema 3 was not defined"),
])
def test_a_declared_size_or_crc_that_fails_is_named_with_its_byte(tmp_path, records, reason):
    with pytest.raises(Damaged) as e:
        list(messages(_file(tmp_path, mcap(records))))
    assert e.value.offset == DATA_START + sum(map(len, records[:-1]))     # the last record's
    assert e.value.reason.startswith(reason), e.value.reason


def test_the_summary_is_checked_against_what_the_data_held(tmp_path):
    data = [schema(), channel(), chunk(message(ns=1)), message(ns=2)]
    good = [schema(), channel(), statistics(2, {1: 2}, chunks=1)]
    assert len(list(messages(_file(tmp_path, mcap(data, good))))) == 2
    for summary, crc, reason in [
            ([statistics(3, {1: 3}, chunks=1)], None, "its statistics count 3 messages, the "
                                                      "file holds 2"),
            ([statistics(2, {1: 2}, chunks=2)], None, "its statistics count 2 chunks, the file "
                                                      "holds 1"),
            ([channel(topic="/other")], None, "channel 1 was defined otherwise before"),
            (good, 1, r"the summary's CRC fails \(recorded 0x00000001"),
            ([message()], None, "message record in the summary")]:
        with pytest.raises(Damaged, match=reason):
            list(messages(_file(tmp_path, mcap(data, summary, summary_crc=crc))))


def test_what_precedes_the_damage_is_given_out_and_nothing_after(tmp_path):
    data = [schema(), channel(), message(ns=1), chunk(message(ns=2), crc=1), message(ns=3)]
    got = []
    with pytest.raises(Damaged, match="chunk record: its CRC fails"):
        for m in messages(_file(tmp_path, mcap(data))):
            got.append(m[2])
    assert got == [1]
    whole = mcap(data[:3])
    with pytest.raises(Damaged, match="the file ends after its last whole record, before its "
                                      "footer"):
        list(messages(_file(tmp_path, whole[:-(8 + 29 + 13)])))     # no data end, no footer
    with pytest.raises(NotMcap, match="not an MCAP file"):
        list(messages(_file(tmp_path, b"PK" + whole[2:])))
    with pytest.raises(Damaged, match="the closing magic is missing or wrong, or bytes follow"):
        list(messages(_file(tmp_path, whole + b"\0")))


def _records(data: bytes) -> list[int]:
    """Where each top-level record of a whole MCAP file begins."""
    at, out = 8, []
    while at < len(data) - 8:
        out.append(at)
        at += 9 + struct.unpack_from("<Q", data, at + 1)[0]
    return out


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    """A real recording of a short StreamFuse call, and the bytes of it."""
    data = _stream.requests(4)
    r = Recorder(tmp_path_factory.mktemp("small"))
    record_stream(r, data, _stream.answers(data))
    r.close()
    (path,) = r.files
    return path, open(path, "rb").read()


def test_a_byte_flipped_anywhere_stops_every_reader_with_a_damaged_file(small, tmp_path):
    path, whole = small
    report = replay.replay(runs([path]), replay.InProcess())
    assert (report.difference, report.cuts, report.calls) == (None, [], 1)
    # every byte of every record's opcode and length, of the last 64 bytes (data end, footer,
    # magic), and a 1-in-37 sample of the rest
    positions = sorted({*(a + k for a in _records(whole) for k in range(9)),
                        *range(len(whole) - 64, len(whole)), *range(0, len(whole), 37)})
    damaged = tmp_path / "damaged.mcap"
    for n, pos in enumerate(positions):
        data = bytearray(whole)
        data[pos] ^= 1 << (pos % 8)
        damaged.write_bytes(bytes(data))
        with pytest.raises((Damaged, NotMcap)):    # what export and view read
            read(damaged)
        if n % 8 == 0:
            try:
                report = replay.replay(runs([damaged]), replay.InProcess())
            except NotMcap:
                assert pos < 8
                continue
            assert report.difference is None and len(report.cuts) == 1, (pos, report)
            assert f"{damaged}: not a complete MCAP recording: byte " in report.cut


def test_a_message_index_read_as_a_message_is_named_as_the_damage_it_is(small, tmp_path):
    # a message index is not covered by the chunk's CRC; its opcode 7 with one bit flipped is
    # a message's 5, which parses (its channel is defined) but is not dqpose's: the data
    # section's CRC, later in the file, says why
    path, whole = small
    (at, *_) = [a for a in _records(whole) if whole[a] == Opcode.MESSAGE_INDEX]
    data = bytearray(whole)
    data[at] = Opcode.MESSAGE
    damaged = tmp_path / "damaged.mcap"
    damaged.write_bytes(bytes(data))
    report = replay.replay(runs([damaged]), replay.InProcess())
    assert report.difference is None and len(report.cuts) == 1, report
    assert f"{damaged}: not a complete MCAP recording: byte " in report.cut
    assert "CRC" in report.cut and "is not what dqpose writes" in report.cut


def test_a_message_that_does_not_parse_is_named_by_every_reader(tmp_path):
    # every CRC holds (the writer computed them), but an answer is not a FusedPose: a file not
    # written by dqpose; export and view stop naming it instead of a traceback
    data = _stream.requests(4)
    answers = _stream.answers(data)
    answers[1] = [b"\xff\xff\xff"]
    r = Recorder(tmp_path / "rec")
    record_stream(r, data, answers)
    r.close()
    (path,) = r.files
    said = f"{path}: not a complete MCAP recording: its message of "
    commands = [["export", path, "--ros2", str(tmp_path / "bag")]]
    if importlib.util.find_spec("viser"):       # the [view] extra
        commands.append(["view", path, "--port", "0"])
    for argv in commands:
        res = subprocess.run([sys.executable, "-m", "dqpose.cli", *argv], capture_output=True,
                             text=True, timeout=120, cwd=ROOT)
        assert res.returncode == 2, (argv, res.stdout, res.stderr)
        assert said in res.stderr and "ns is not a dqpose.v1.FusedPose" in res.stderr, \
            (argv, res.stderr)
        assert "Traceback" not in res.stderr
