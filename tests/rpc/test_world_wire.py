"""World.Publish's C path (dqpose.rpc.wire.publish_from_wire, from world_publish.publish_bytes)
against the protobuf path it replaces: on generated, damaged and re-encoded requests a world fed the
bytes acks exactly what a world fed the parsed messages acks (errors and their texts) and holds
the same rows, bit for bit."""
from __future__ import annotations

import numpy as np
from google.protobuf.message import DecodeError
from hypothesis import given, settings
from hypothesis import strategies as st

from dqpose.rpc import world_publish
from dqpose.rpc._proto.dqpose.v1 import world_pb2 as wpb
from dqpose.rpc.wire import publish_from_wire, publish_head
from dqpose.rpc.world import World
from tests.rpc._mutate import damaged
from tests.rpc.test_fusion_wire import good, measurement
from tests.rpc.test_wire import PADS, reencode

NESTED = {"publish": {1: "measurement"}, "measurement": {4: "pose"}, "pose": {1: None, 2: None}}


@st.composite
def requests(draw, r: int):
    n = draw(st.integers(0, 5))
    return wpb.PublishRequest(measurements=[draw(measurement(0.01 * r + 0.002 * k))
                                            for k in range(n)],
                              producer=draw(st.sampled_from(["", "cam-1", "arm"])),
                              sequence=draw(st.sampled_from([0, r, r + 2])))


def run_both(datas: list[bytes], decoded: list | None = None) -> None:
    """The same request bytes into two worlds, one through each path: the same acks, the same
    rows in each body's window."""
    server = World()
    by_bytes, by_message = server.hub("bytes", make=True), server.hub("message", make=True)
    for r, data in enumerate(datas):
        got = server.publish_bytes(by_bytes, data, r, "anonymous")
        try:
            request = wpb.PublishRequest.FromString(data)
        except DecodeError:
            assert got.errors[0].details.startswith(f"requests[{r}]: not a valid")
            continue
        want = world_publish.publish(by_message, request, r, "anonymous", server.max_poses)
        assert got.SerializeToString() == want.SerializeToString()
        if decoded is not None:
            decoded.append(publish_from_wire(data) is not None)
    a, b = by_bytes.world.tracker, by_message.world.tracker
    assert by_bytes.measurements == by_message.measurements
    assert a.bodies == b.bodies
    for body in a.bodies:
        for x, y in zip(a.window_of(body), b.window_of(body)):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


@settings(max_examples=150, deadline=None)
@given(st.lists(st.integers(0, 4), min_size=1, max_size=4), st.data())
def test_generated_requests_ack_as_the_protobuf_path(sizes, data):
    run_both([data.draw(requests(r)).SerializeToString() for r in range(1, len(sizes) + 1)])


@settings(max_examples=200, deadline=None)
@given(requests(1), st.data())
def test_damaged_requests_ack_as_the_protobuf_path(req, data):
    run_both([damaged(req.SerializeToString(), data)])


@settings(max_examples=100, deadline=None)
@given(requests(1), st.data())
def test_padded_varints_ack_as_the_protobuf_path(req, data):
    run_both([reencode(req.SerializeToString(), "publish", lambda: data.draw(PADS), NESTED)])


def test_plain_requests_take_the_c_path():
    datas = [wpb.PublishRequest(measurements=good(4, 0.01 * r), producer="cam-1",
                                sequence=r + 1).SerializeToString() for r in range(5)]
    decoded: list = []
    run_both(datas, decoded)
    assert decoded == [True] * 5
    # what it leaves to protobuf: an unknown field, a producer that is not a string's field
    unknown = datas[0] + b"\x38\x01"                     # field 7, a varint
    wrong = datas[0] + b"\x10\x01"                       # field 2 as a varint
    assert publish_from_wire(unknown) is None and publish_from_wire(wrong) is None


def _head_is_protobufs(data: bytes) -> None:
    head = publish_head(data)
    try:
        request = wpb.PublishRequest.FromString(data)
    except DecodeError:     # the head may read: its measurements then fail to decode
        return
    if head is not None:
        assert head == (request.producer, request.sequence, len(request.measurements))


@settings(max_examples=300, deadline=None)
@given(requests(1), st.data())
def test_a_requests_head_is_read_in_c_as_protobuf_reads_it(req, data):
    """publish_head (World.publish_bytes's producer, sequence and count, no protobuf parse) is
    protobuf's reading of damaged bytes that protobuf reads, or None (then protobuf reads them);
    run_both's tests above show bytes protobuf refuses acked as it does."""
    _head_is_protobufs(damaged(req.SerializeToString(), data))
    _head_is_protobufs(reencode(req.SerializeToString(), "publish", lambda: data.draw(PADS),
                                NESTED))


def test_a_head_the_c_leaves_to_protobuf():
    data = wpb.PublishRequest(measurements=good(2, 0.0), producer="cam-1",
                              sequence=7).SerializeToString()
    assert publish_head(data) == ("cam-1", 7, 2)
    # the last producer and sequence given are protobuf's
    again = data + wpb.PublishRequest(producer="arm", sequence=9).SerializeToString()
    assert publish_head(again) == ("arm", 9, 2) == (
        wpb.PublishRequest.FromString(again).producer,
        wpb.PublishRequest.FromString(again).sequence, 2)
    assert publish_head(wpb.PublishRequest(producer="kamera-é").SerializeToString()) is None
    assert publish_head(data + b"\x38\x01") is None        # an unknown field
    bad_utf8 = b"\x12\x02\xc3\x28"                           # producer of invalid UTF-8
    assert publish_head(bad_utf8) is None
    run_both([bad_utf8, data])
