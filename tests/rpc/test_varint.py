"""dqpose.rpc.varint: the bytes protobuf writes, for any values."""
from __future__ import annotations

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from dqpose.rpc._proto.dqpose.v1 import fusion_pb2 as fpb
from dqpose.rpc.varint import packed, varint

_DOUBLES = st.lists(st.floats(allow_nan=True, allow_infinity=True, width=64), max_size=300)


@given(_DOUBLES, st.lists(st.booleans(), max_size=300))
def test_packed_is_protobufs_bytes(doubles, bools):
    """Packed doubles (NaN, infinities, -0.0 and lengths of one and two varint bytes included)
    and bools, each field alone and empty ones left out, as protobuf serializes them."""
    assert packed(13, np.array(doubles)) == fpb.FusedPose(nis=doubles).SerializeToString()
    assert packed(14, np.array(bools, dtype=bool), "u1") == fpb.FusedPose(
        tested=bools).SerializeToString()
    # a field number past 15 takes a two-byte tag
    assert packed(22, np.array(doubles)) == fpb.FusedPose(twist=doubles).SerializeToString()


@given(st.integers(min_value=0, max_value=2**64 - 1))
def test_varint_reads_back_as_protobuf_writes_it(v):
    assert fpb.FusedPose(measurements=[v]).SerializeToString() == b"\x9a\x01" + varint(
        len(varint(v))) + varint(v)
