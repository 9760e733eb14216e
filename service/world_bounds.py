"""What a world holds at most (:class:`WorldBounds`) and the refusals of what would take it past
that, each a :class:`~dqpose.errors.WorldError` naming the bound."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

from dqpose import limits as _limits
from dqpose.errors import WorldError
from dqpose.names import quoted


@dataclass(frozen=True)
class WorldBounds:
    """What a world holds at most; a refusal names the bound ("bodies: 1001 is above the
    world's 1000"). ``max_measurements_per_body``: measurements a body's buffer keeps (the
    server's ``Limits.max_window`` when the world has limits); ``max_measurements``: all bodies'
    (None: ``max_bodies`` times that)."""
    max_bodies: int = 1000
    max_sources: int = 64
    max_measurements_per_body: int = _limits.Limits().max_window
    max_buffer: float = 60.0
    max_measurements: Optional[int] = None
    max_statics: int = 1000
    max_static_bodies: int = 1000


#: the bounds of a world made without any
DEFAULT = WorldBounds()


def over(field: str, value, bound: str, limit, unit: str = "") -> WorldError:
    """``field``'s ``value`` above the world's ``bound`` (RESOURCE_EXHAUSTED on the wire)."""
    u = f" {unit}" if unit else ""
    return WorldError(None, field, f"{value:.6g}{u} is above the world's {bound} {limit:.6g}{u}",
                      limit=bound)


def over_bounds(bodies, sources, errors: dict, known, named, b: WorldBounds) -> None:
    """The rows (not refused yet) that would take the world past ``max_bodies`` or
    ``max_sources`` (``known`` bodies and ``named`` sources held), refused in ``errors``."""
    new_bodies: set = set()
    new_sources: set = set()
    for k, (body, src) in enumerate(zip(bodies, sources)):
        if k in errors or not isinstance(body, str) or not isinstance(src, str):
            continue
        refusal = ((body and _beyond(k, "body", body, known, new_bodies, "max_bodies",
                                     b.max_bodies))
                   or _beyond(k, "source", src, named, new_sources, "max_sources",
                              b.max_sources))
        if refusal:
            errors[k] = refusal
            continue
        if body and body not in known:
            new_bodies.add(body)
        if src not in named:
            new_sources.add(src)


def _beyond(k: int, field: str, name: str, held, new: set, bound: str,
            limit: int) -> Optional[WorldError]:
    """The refusal of row ``k`` when ``name`` would be one ``field`` more than ``limit`` (the
    world's ``bound``): ``held`` ones are in the world, ``new`` ones this request adds; a row
    refused for either name adds neither."""
    if name in held or name in new or len(held) + len(new) < limit:
        return None
    return WorldError(k, field, f"{quoted(name)} would be {field} {len(held) + len(new) + 1}, "
                                f"above the world's {bound} {limit}")
