"""The backends by name: :data:`ARMS` and :data:`SOURCES` (name -> ``"module:class"``, a module
imported only when opened) and :func:`split_backend`, the one reading of ``<backend>:<channel>``.
Below :mod:`dqpose.drivers` and :mod:`dqpose.drivers.spec`, which both read them."""
from __future__ import annotations

from typing import Optional

#: arm backends: name -> "module:class"; the class's ``open(channel, **kwargs)`` makes one
ARMS = {
    "ur": "dqpose.drivers.ur:URArm",
    "piper": "dqpose.drivers.piper:PiperArm",
}
#: pose source backends, the same way
SOURCES = {
    "charuco": "dqpose.drivers.camera:CharucoCamera",
}


def split_backend(kind: str, table: dict, spec: str, whole: Optional[str] = None,
                   grammar: str = "<backend>:<channel>") -> tuple[str, str]:
    """``spec``'s backend (a name in ``table``) and channel, else ``ValueError`` naming ``kind``
    and ``whole`` (the text ``spec`` is part of; ``grammar``: how it is written)."""
    whole = spec if whole is None else whole
    name, sep, channel = spec.partition(":")
    if name not in table:
        raise ValueError(f"{kind}: unknown backend {name!r} in {whole!r}; known: "
                         f"{', '.join(sorted(table))} (as '{grammar}')")
    if not sep or not channel:
        raise ValueError(f"{kind}: {whole!r} has no channel; expected '{name}:<channel>'")
    return name, channel
