"""The ``dqpose.v1.Blending`` messages' own vocabulary: the ``Method`` enum <-> the names of
:data:`dqpose.dq.METHODS`. Poses and stamped poses are :mod:`dqpose.rpc.geometry`'s; the request
and answer bytes of the C fast paths, :mod:`dqpose.rpc.wire`'s.
"""
from __future__ import annotations

from dqpose import dq
from dqpose.rpc._proto.dqpose.v1 import blending_pb2 as pb

# dq.METHODS by name: its "dlb" is METHOD_DLB (tests/rpc/test_geometry.py checks the values too).
METHOD_ENUMS = {name: pb.Method.Value(f"METHOD_{name.upper()}") for name in dq.METHODS}
#: Blend's method for METHOD_UNSPECIFIED (blending.proto says so) and for each Method value
METHOD_NAMES = {pb.METHOD_UNSPECIFIED: "dib", **{code: name for name, code in METHOD_ENUMS.items()}}
