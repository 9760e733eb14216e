"""Protobuf's varints and packed repeated scalars, as the wire bytes protobuf writes for them."""
from __future__ import annotations

import numpy as np


def varint(v: int) -> bytes:
    """The unsigned varint of ``v`` (>= 0): seven bits a byte, low first."""
    out = bytearray()
    while v >= 0x80:
        out.append(v & 0x7F | 0x80)
        v >>= 7
    out.append(v)
    return bytes(out)


def packed(field: int, values, dtype: str = "<f8") -> bytes:
    """Repeated scalar field ``field`` packed: its tag, its length and the values' bytes, one
    ``dtype`` each (``<f8``: doubles; ``u1``: bools, whose varints are one byte). Empty for no
    values: protobuf leaves an empty field out. The values' bytes are written at once rather
    than value by value: a fused pose's residuals, NIS and distances are hundreds of doubles."""
    data = np.ascontiguousarray(values, dtype=dtype).tobytes()
    return varint(field << 3 | 2) + varint(len(data)) + data if data else b""
