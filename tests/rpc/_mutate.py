"""Damage for the wire tests: the fast paths must refuse or read exactly what protobuf does."""
from __future__ import annotations

from hypothesis import strategies as st


def damaged(raw: bytes, data) -> bytes:
    """``raw`` with 1-3 bytes overwritten at random and cut at a random length (``data``: a
    hypothesis ``st.data()``)."""
    raw = bytearray(raw)
    if raw:
        for _ in range(data.draw(st.integers(1, 3))):
            i = data.draw(st.integers(0, len(raw) - 1))
            raw[i] = data.draw(st.integers(0, 255))
        raw = raw[:data.draw(st.integers(0, len(raw)))]
    return bytes(raw)
