"""A waypoint given in a body's frame ("the tool 10 cm above the box") resolved through a
:class:`dqpose.world.World` at plan time: ``T_base_tool = T_base_world T_world_body T_body_tool``
with the body's newest fused pose, and the body's covariance carried to the tool."""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from dqpose import dq, lie
from dqpose.errors import Infeasible


class Resolved(NamedTuple):
    pose: np.ndarray          # (8,) T_base_tool
    covariance: np.ndarray    # (6, 6) right perturbation of pose: the body's, carried to the tool
    time: float               # the body's fused pose's time


def resolve(world, body: str, T_body_tool: np.ndarray, field: str,
            T_world_base: np.ndarray | None = None) -> Resolved:
    """``T_body_tool`` in the base frame (``T_world_base`` None: the world frame is the base).
    An unknown body, or one whose newest measurement is more than the world's ``buffer`` older
    than the newest measurement of any body (it stopped being seen), is :class:`Infeasible`
    naming it under ``field``."""
    bodies = world.bodies
    if body not in bodies:
        known = ", ".join(sorted(bodies)) or "none yet"
        raise Infeasible(f"{field}: body {body!r} is not in the world (its bodies: {known})")
    newest = max(world.newest(b) for b in bodies)
    own = world.newest(body)
    if newest - own > world.options.buffer:
        raise Infeasible(f"{field}: body {body!r} is stale: its newest measurement is at "
                         f"{own:.6g} s, {newest - own:.6g} s before the world's newest "
                         f"({newest:.6g} s), beyond its buffer of {world.options.buffer:.6g} s")
    p = world.pose(body)
    T_world_tool = dq.mul(p.pose, T_body_tool)
    pose = T_world_tool if T_world_base is None else dq.mul(dq.inv(T_world_base),
                                                             T_world_tool)
    return Resolved(pose, lie.cov_compose(p.covariance, T_body_tool, None), float(p.time))
