"""The ``dqpose.v1.World`` messages <-> :mod:`dqpose.world`: a ``WorldConfig`` as the World's
sources, arms and options (the proto's zeros made the domain's defaults here) and back, and a
:class:`dqpose.world.BodyPose` as a ``FusedPose`` or a ``RelativePose`` (:class:`Encoder`: how a
hub writes its answers). Measurements, sources and fused poses convert as Fusion's do
(:mod:`dqpose.rpc.fusion_convert`)."""
from __future__ import annotations

import math

import numpy as np

from dqpose import _dqcore as _c
from dqpose import frames, world
from dqpose.errors import FieldError
from dqpose.names import name_problem
from dqpose.rpc._proto.dqpose.v1 import fusion_pb2 as fpb
from dqpose.rpc._proto.dqpose.v1 import world_pb2 as pb
from dqpose.rpc.calls import readable
from dqpose.rpc.fusion_convert import (
    DEFAULT_MAX_EXTRAPOLATION,
    options_from_msg,
    options_msg,
    source_msgs,
    sources_from_msg,
)
from dqpose.rpc.geometry import COVARIANCE_SIZE, dq_to_pose, optional_pose
from dqpose.rpc.wire import fused_pose_bytes


def config_from_msg(msg: pb.WorldConfig, field: str = "config"):
    """``(sources, arms, WorldOptions)`` of a ``WorldConfig``; FieldError naming the field."""
    o = msg.options
    if o.sources:
        raise FieldError(f"{field}.options.sources: give the sources in {field}.sources")
    if o.time:
        raise FieldError(f"{field}.options.time: the world answers at its ticks and lookups; "
                         f"leave it 0")
    options = options_from_msg(o, f"{field}.options")
    sources = sources_from_msg(msg.sources, f"{field}.sources")
    arms: dict[str, str] = {}
    for k, a in enumerate(msg.arms):
        if a.arm in arms:
            raise FieldError(f"{field}.arms[{k}].arm: {a.arm!r} is given twice")
        arms[a.arm] = a.source
    kw = {}
    for name in ("buffer", "max_delay"):
        v = getattr(msg, name)
        if not (math.isfinite(v) and v >= 0.0):
            raise FieldError(f"{field}.{name}: must be finite and >= 0 (0: the default), got "
                             f"{v!r}")
        if v:
            kw[name] = float(v)
    if options.window:
        kw["window"] = float(options.window)
    wo = world.WorldOptions(robust=options.robust, probability=options.probability,
                            max_skew=options.max_skew,
                            max_extrapolation=options.max_extrapolation,
                            twist_covariance=options.twist_covariance,
                            acceleration_psd=options.acceleration_psd, **kw)
    return sources, arms, wo


def frames_from_msg(msg: pb.WorldConfig, field: str = "config"):
    """``(statics, static_bodies)`` of a ``WorldConfig`` (:class:`dqpose.frames.Static` s; the
    domain checks names, poses and covariances); FieldError naming the field."""
    statics = []
    for k, s in enumerate(msg.statics):
        where = f"{field}.statics[{k}]"
        if not s.HasField("pose"):
            raise FieldError(f"{where}.pose: required (T_parent_child)")
        n = len(s.covariance)
        if n not in (0, COVARIANCE_SIZE):
            raise FieldError(f"{where}.covariance: expected {COVARIANCE_SIZE} values (6x6, "
                             f"row-major, rotation first) or none, got {n}")
        cov = np.array(s.covariance, dtype=np.float64).reshape(6, 6) if n else None
        pose = optional_pose(s, "pose", where)
        assert pose is not None                 # it has the field
        statics.append(frames.Static(s.parent, s.child, pose, cov))
    return tuple(statics), tuple(msg.static_bodies)


def frames_msgs(tree, msg: pb.WorldConfig) -> pb.WorldConfig:
    """``msg`` with the statics and static bodies of :class:`dqpose.frames.FrameTree` ``tree``
    (or of the client's arguments: ``(statics, static_bodies)``)."""
    statics, static_bodies = ((tree.statics, tree.static_body_names)
                              if isinstance(tree, frames.FrameTree) else tree)
    for s in statics:
        m = msg.statics.add(parent=s.parent, child=s.child)
        dq_to_pose(np.asarray(s.pose, dtype=np.float64), m.pose)
        if s.covariance is not None:
            m.covariance.extend(np.asarray(s.covariance, dtype=np.float64).ravel().tolist())
    msg.static_bodies.extend(static_bodies)
    return msg


def config_msg(sources, arms, options) -> pb.WorldConfig:
    """The ``WorldConfig`` of a world's sources, arms and :class:`dqpose.world.WorldOptions`
    (the configuration in force, defaults filled in)."""
    o = options_msg(robust=options.robust, probability=options.probability,
                    max_skew=options.max_skew, max_extrapolation=options.max_extrapolation,
                    window=options.window, twist_covariance=options.twist_covariance,
                    acceleration_psd=options.acceleration_psd)
    msg = pb.WorldConfig(options=o, buffer=float(options.buffer),
                         max_delay=float(options.max_delay))
    source_msgs(sources, msg.sources)
    for arm, source in sorted(arms.items()):
        msg.arms.add(arm=arm, source=source)
    return msg


def world_config(sources=(), arms=None, *, robust: bool = False, probability: float = 0.0,
                 max_skew: float | None = None,
                 max_extrapolation: float | None = DEFAULT_MAX_EXTRAPOLATION,
                 window: float = 0.0, twist_covariance=None, acceleration_psd=None,
                 buffer: float = 0.0, max_delay: float = 0.0, statics=(),
                 static_bodies=()) -> pb.WorldConfig:
    """Client side: a ``WorldConfig`` from the domain's arguments (``sources``:
    :class:`dqpose.fusion.Source`, ``arms`` arm name -> source name, ``statics``:
    :class:`dqpose.frames.Static`, ``static_bodies`` names; 0: the server's default)."""
    o = options_msg(robust=robust, probability=probability, max_skew=max_skew,
                    max_extrapolation=max_extrapolation, window=window,
                    twist_covariance=twist_covariance, acceleration_psd=acceleration_psd)
    msg = pb.WorldConfig(options=o, buffer=float(buffer), max_delay=float(max_delay))
    source_msgs(sources, msg.sources)
    for arm, source in (arms or {}).items():
        msg.arms.add(arm=arm, source=source)
    return frames_msgs((statics, static_bodies), msg)


def subscribe_names(request: pb.SubscribeRequest) -> str | None:
    """What is wrong with a ``SubscribeRequest``'s names (``bodies``, ``relative_to``: a body
    or "", the world frame), naming the field; None when they are names."""
    for i, body in enumerate(request.bodies):
        problem = name_problem(body)
        if problem is not None:
            return f"bodies[{i}]: {problem}"
    problem = name_problem(request.relative_to, empty=True)
    return None if problem is None else f"relative_to: {problem}"


def body_pose_bytes(p, request: int = 0, measurements=()) -> bytes:
    """A :class:`dqpose.world.BodyPose` with its fit (a Subscribe answer) as ``FusedPose``
    bytes (:func:`dqpose.rpc.wire.fused_pose_bytes`): every field of its fit, its own pose and
    covariance (a relative one's), ``request`` and the fused ``measurements``."""
    assert p.fused is not None          # a tick's answer is a body's fit
    return fused_pose_bytes(p.fused, p.body, p.time, request, measurements, p.pose,
                            p.covariance)


def relative_pose_bytes(p) -> bytes:
    """A :class:`dqpose.world.BodyPose` (``relative``'s, a Lookup's answer) as ``RelativePose``
    bytes, written in C (service/csrc/lookup.c): the bytes of :func:`relative_msg`'s message."""
    return _c.relative_pose_bytes(p.pose, p.covariance, float(p.time))


def error_bytes(body: str, time: float, request: int, text: str) -> bytes:
    """A Subscribe answer saying why ``body`` at ``time`` (0: none) was not answered after
    request ``request``: a ``FusedPose`` error entry's bytes."""
    return fpb.FusedPose(body=body, time=time, request=request, error=fpb.FuseError(
        request=request, measurement=-1, details=readable(text))).SerializeToString()


class Encoder:
    """The World service's answers as the hubs write them (:class:`dqpose.hub.Encoder`)."""
    fused = staticmethod(body_pose_bytes)
    wire = True
    error = staticmethod(error_bytes)

    @staticmethod
    def fit_error(e: Exception) -> str:
        return str(e)

    relative = staticmethod(relative_pose_bytes)


def relative_msg(p) -> pb.RelativePose:
    """A :class:`dqpose.world.BodyPose` (``relative``'s) as a ``RelativePose``."""
    msg = pb.RelativePose(time=float(p.time))
    dq_to_pose(np.asarray(p.pose, dtype=np.float64), msg.pose)
    msg.covariance.extend(np.asarray(p.covariance, dtype=np.float64).ravel().tolist())
    return msg
