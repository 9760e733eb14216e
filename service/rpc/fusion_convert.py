"""The ``dqpose.v1.Fusion`` messages <-> the arguments and results of :mod:`dqpose.fusion`:
``Measurement`` s to arrays (each checked, a bad one named ``measurements[3].time: ...``),
``FusionOptions`` to the domain's options (the proto's zeros made the domain's defaults here),
a ``FuseRequest`` to :func:`dqpose.fusion.fuse`'s arguments with the checks Fuse makes of it
(what ``dqpose fuse --local`` runs too), and :class:`dqpose.fusion.Fused` to ``FusedPose`` and
back (the client's).
"""
from __future__ import annotations

import itertools
import math
from typing import Callable, NamedTuple

import numpy as np

from dqpose import dq, fusion, limits
from dqpose.errors import FieldError, rename
from dqpose.names import check_name, quoted
from dqpose.rpc import DEFAULT_MAX_POSES
from dqpose.rpc._proto.dqpose.v1 import fusion_pb2 as fpb
from dqpose.rpc.checks import check_count, field_named
from dqpose.rpc.geometry import (
    COVARIANCE_SIZE,
    dq_to_pose,
    optional_pose,
    pose_arrays,
    pose_from_row,
    pose_msgs,
    pose_to_dq,
)
from dqpose.rpc.varint import packed

DEFAULT_PROBABILITY = fusion.DEFAULT_PROBABILITY
DEFAULT_MAX_EXTRAPOLATION = fusion.DEFAULT_MAX_EXTRAPOLATION
#: StreamFuse's window (s) for FusionOptions.window 0
DEFAULT_WINDOW = 0.2

class Measurements(NamedTuple):
    """Repeated ``Measurement`` as arrays; ``index[k]`` is the message's measurement of row k."""
    # (n,) int; shadows tuple.index(), which no caller uses, for the name the fields go by
    index: np.ndarray  # type: ignore[assignment]
    bodies: tuple[str, ...]
    sources: tuple[str, ...]
    times: np.ndarray          # (n,)
    poses: np.ndarray          # (n, 8) T_frame_body, unit
    covariances: np.ndarray    # (n, 6, 6), as given (the domain checks SPD and finiteness)


def measurements_to_arrays(ms, field: str = "measurements",
                           errors: list | None = None, first: int = 0) -> Measurements:
    """Repeated ``Measurement`` to :class:`Measurements`. A bad measurement raises the
    :class:`FieldError` naming it (``{field}[i].time: ...``); with ``errors`` (a list) it is
    appended there as ``(i, FieldError)`` and left out instead. Each field is read for all
    measurements at once and checked in NumPy; only the measurements with a problem are looked
    at one by one, to name it. ``first``: the number the texts give ``ms[0]`` (``ms`` a part of
    the field)."""
    ms = list(ms)
    n = len(ms)
    times = np.array([m.time for m in ms], dtype=np.float64)
    weights = np.array([m.weight for m in ms], dtype=np.float64)
    counts = np.array([len(m.covariance) for m in ms], dtype=np.int64)
    flat = np.array([(o.w, o.x, o.y, o.z, t.x, t.y, t.z) for o, t in
                     ((m.pose.orientation, m.pose.position) for m in ms)],
                    dtype=np.float64).reshape(-1, 7)
    full = counts == COVARIANCE_SIZE
    bad: dict[int, FieldError] = {}
    problems: tuple[tuple[np.ndarray, Callable[[int], str]], ...]
    if full.all() and not weights.any() and np.isfinite(times).all():
        # the common case, every measurement with its 36 values: one pass, no checks to name
        covs = np.fromiter(itertools.chain.from_iterable(m.covariance for m in ms),
                           np.float64, n * COVARIANCE_SIZE).reshape(n, fusion.DOF, fusion.DOF)
        problems = ()
    else:
        covs = np.empty((n, COVARIANCE_SIZE))
        for k in np.flatnonzero(full).tolist():
            covs[k] = ms[k].covariance
        covs = covs.reshape(n, fusion.DOF, fusion.DOF)
        iso = counts == 0
        w = np.where(weights == 0.0, 1.0, weights)        # weight 0 means 1
        with np.errstate(over="ignore"):     # a subnormal weight: inf, refused by the domain
            covs[iso] = np.eye(fusion.DOF) / w[iso, None, None]
        problems = (
        (~np.isfinite(times), lambda i: f"time: must be finite, got {ms[i].time!r}"),
        (~iso & ~full, lambda i: f"covariance: expected {COVARIANCE_SIZE} values (6x6, "
                                 f"row-major, rotation first) or none, got {counts[i]}"),
        (full & (weights != 0.0), lambda i: "weight: give a covariance or a weight, not both"),
        (iso & ~(np.isfinite(w) & (w > 0.0)),
         lambda i: f"weight: must be positive and finite (0 means 1), got {float(w[i])!r}"))
    for mask, text in problems:
        for i in np.flatnonzero(mask).tolist():
            bad.setdefault(i, FieldError(f"{field}[{first + i}].{text(i)}"))
    keep = np.ones(n, dtype=bool)
    if bad:
        keep[list(bad)] = False
    index = np.flatnonzero(keep)
    try:
        poses = dq.from_pose(flat[index, :4], flat[index, 4:])
    except ValueError:
        # Name the measurement, not the row: one at a time to find every bad one.
        for i in index.tolist():
            try:
                pose_from_row(flat[i], f"{field}[{first + i}].pose")
            except FieldError as e:
                bad[i] = e
                keep[i] = False
        index = np.flatnonzero(keep)
        poses = dq.from_pose(flat[index, :4], flat[index, 4:])
    if bad:
        found = sorted(bad.items())
        if errors is None:
            raise found[0][1]
        errors.extend(found)
        errors.sort(key=lambda x: x[0])
    return Measurements(index, tuple(ms[i].body for i in index), tuple(ms[i].source for i in index),
                        times[index], poses, covs[index])


def wire_measurement_error(data: bytes, span, field: str, i: int) -> FieldError:
    """The error :func:`measurements_to_arrays` names measurement ``i`` (its bytes at ``span``)
    with: one Measurement parsed and checked the protobuf way, so the text has one source."""
    msg = fpb.Measurement.FromString(data[int(span[0]):int(span[0]) + int(span[1])])
    errors: list = []
    measurements_to_arrays([msg], field, errors, first=i)
    return errors[0][1]



class Options(NamedTuple):
    """``FusionOptions`` as the domain's arguments (:meth:`fuse_kwargs` those of
    :func:`fusion.fuse` and :class:`fusion.Tracker`)."""
    robust: bool
    time: float                      # 0: the newest measurement's
    sources: tuple[fusion.Source, ...]
    probability: float
    max_skew: float | None = None
    max_extrapolation: float | None = DEFAULT_MAX_EXTRAPOLATION
    window: float = 0.0              # 0: DEFAULT_WINDOW (StreamFuse)
    twist_covariance: np.ndarray | None = None
    acceleration_psd: np.ndarray | None = None

    def fuse_kwargs(self) -> dict:
        return dict(sources=self.sources, robust=self.robust, probability=self.probability,
                    max_skew=self.max_skew, max_extrapolation=self.max_extrapolation,
                    twist_covariance=self.twist_covariance,
                    acceleration_psd=self.acceleration_psd)


def sources_from_msg(msgs, field: str = "options.sources") -> tuple[fusion.Source, ...]:
    """Repeated ``Source`` to :class:`fusion.Source` s: frames converted, an
    ``extrinsic_covariance`` of 36 values made 6x6 (the domain checks it is SPD)."""
    sources = []
    for k, s in enumerate(msgs):
        where = f"{field}[{k}]"
        check_name(s.name, f"{where}.name")
        cov = None
        n = len(s.extrinsic_covariance)
        if n not in (0, COVARIANCE_SIZE):
            raise FieldError(f"{where}.extrinsic_covariance: expected {COVARIANCE_SIZE} values "
                             f"(6x6, row-major, rotation first) or none, got {n}")
        if n:
            cov = np.array(
                s.extrinsic_covariance, dtype=np.float64).reshape(fusion.DOF, fusion.DOF)
        sources.append(fusion.Source(s.name, optional_pose(s, "extrinsic", where),
                                     optional_pose(s, "body_offset", where), s.latency,
                                     s.latency_sigma or None, cov, s.parent))
    return tuple(sources)


def source_msgs(sources, out) -> None:
    """:class:`fusion.Source` s appended to the repeated ``Source`` field ``out``."""
    for s in sources or ():
        msg = out.add(name=s.name, latency=float(s.latency),
                      latency_sigma=float(s.latency_sigma or 0.0),
                      parent=getattr(s, "parent", ""))
        if s.extrinsic is not None:
            dq_to_pose(np.asarray(s.extrinsic, dtype=np.float64), msg.extrinsic)
        if s.body_offset is not None:
            dq_to_pose(np.asarray(s.body_offset, dtype=np.float64), msg.body_offset)
        c = getattr(s, "extrinsic_covariance", None)
        if c is not None:
            msg.extrinsic_covariance.extend(np.asarray(c, dtype=np.float64).ravel().tolist())


def options_from_msg(options, field: str = "options") -> Options:
    """``FusionOptions`` to :class:`Options`: frames converted and the proto's zeros turned into
    the domain's defaults here; the domain checks the rest (names, duplicates, signs, the twist
    prior) and its errors are renamed to these fields."""
    sources = sources_from_msg(options.sources, f"{field}.sources")
    if not math.isfinite(options.time):
        raise FieldError(f"{field}.time: must be finite, got {options.time!r}")
    p = options.probability or DEFAULT_PROBABILITY
    if not 0.0 < p < 1.0:
        raise FieldError(f"{field}.probability: must be within (0, 1) (0 means "
                         f"{DEFAULT_PROBABILITY}), got {options.probability!r}")
    matrices = {}
    for name in ("twist_covariance", "acceleration_psd"):
        k = len(getattr(options, name))
        if k not in (0, COVARIANCE_SIZE):
            raise FieldError(f"{field}.{name}: expected {COVARIANCE_SIZE} values (6x6, "
                             f"row-major, rotation first) or none, got {k}")
        matrices[name] = np.array(getattr(options, name), dtype=np.float64).reshape(
            fusion.DOF, fusion.DOF) if k else None
    extrapolation = options.max_extrapolation or DEFAULT_MAX_EXTRAPOLATION
    return Options(
        bool(options.robust), float(options.time), tuple(sources), p,
        max_skew=options.max_skew or None,
        max_extrapolation=None if extrapolation == math.inf else extrapolation,
        window=options.window, **matrices)


def options_msg(robust: bool = False, time: float = 0.0, sources=(), probability: float = 0.0,
                max_skew: float | None = None,
                max_extrapolation: float | None = DEFAULT_MAX_EXTRAPOLATION,
                window: float = 0.0, twist_covariance=None, acceleration_psd=None):
    """``FusionOptions`` from the domain's arguments (``sources``: :class:`fusion.Source`;
    ``max_extrapolation`` None: unbounded)."""
    msg = fpb.FusionOptions(robust=bool(robust), time=float(time),
                            probability=float(probability or 0.0),
                            max_skew=float(max_skew or 0.0),
                            max_extrapolation=math.inf if max_extrapolation is None
                            else float(max_extrapolation),
                            window=float(window or 0.0))
    for name, value in (("twist_covariance", twist_covariance),
                        ("acceleration_psd", acceleration_psd)):
        if value is not None:
            c = np.asarray(value, dtype=np.float64)
            if c.shape != (fusion.DOF, fusion.DOF):
                raise ValueError(f"{name}: expected shape (6, 6), got {c.shape}")
            getattr(msg, name).extend(c.ravel().tolist())
    source_msgs(sources, msg.sources)
    return msg


def measurement_columns(poses, covariances, weights, names, bodies, times):
    """The client's measurement arrays checked for shape: ``(q, t, covariances, weights, names,
    bodies, times)``, ``q``/``t`` the wire's (:func:`pose_arrays`), absent columns None."""
    a = np.asarray(poses, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 8:
        raise ValueError(f"poses: expected shape (n, 8), got {a.shape}")
    n = len(a)

    def column(x, name, tail=()):
        if x is None:
            return None
        if isinstance(x, str):
            raise ValueError(f"{name}: expected one value per measurement, got a string")
        c = list(x) if not tail else np.asarray(x, dtype=np.float64)
        if len(c) != n or (tail and c.shape[1:] != tail):
            shape = ", ".join(str(k) for k in (n,) + tail)
            raise ValueError(f"{name}: expected ({shape}) for {n} poses, got "
                             f"{getattr(c, 'shape', (len(c),))}")
        return c

    covariances = column(covariances, "covariances", (fusion.DOF, fusion.DOF))
    weights, names = column(weights, "weights"), column(names, "names")
    bodies, times = column(bodies, "bodies"), column(times, "times")
    if covariances is not None and weights is not None:
        raise ValueError("weights: give covariances or weights, not both")
    return (*pose_arrays(a), covariances, weights, names, bodies, times)


def measurement_msgs(poses, covariances=None, weights=None, names=None, bodies=None,
                     times=None) -> list:
    """``Measurement`` messages from arrays (client side; values as given, the server checks
    them): ``poses`` ``(n, 8)``, ``covariances`` ``(n, 6, 6)`` or ``weights`` ``(n,)`` or
    neither, and per-measurement ``names`` (sources), ``bodies`` and ``times``."""
    q, t, covariances, weights, names, bodies, times = measurement_columns(
        poses, covariances, weights, names, bodies, times)
    out = []
    for i, m in enumerate(pose_msgs(q, t)):
        msg = fpb.Measurement(pose=m, source=names[i] if names else "",
                              body=bodies[i] if bodies else "",
                              time=float(times[i]) if times is not None else 0.0)
        if covariances is not None:
            msg.covariance.extend(covariances[i].ravel().tolist())
        elif weights is not None:
            msg.weight = float(weights[i])
        out.append(msg)
    return out


STATUS_ENUMS = {s: s.value + 1 for s in fusion.Status}     # proto 0 is an error entry
STATUS_NAMES = {v: k for k, v in STATUS_ENUMS.items()}


def fused_to_msg(f: fusion.Fused, body: str, time: float, out=None):
    """A :class:`fusion.Fused` into a ``FusedPose`` (written into ``out`` when given)."""
    msg = fpb.FusedPose() if out is None else out
    msg.body, msg.time = body, float(time)
    dq_to_pose(f.mean, msg.pose)
    msg.inliers.extend(f.inliers.tolist())
    msg.rejected.extend(r.index for r in f.rejected)
    msg.rejected_sources.extend(r.source for r in f.rejected)
    msg.reasons.extend(r.reason for r in f.rejected)
    msg.chi2, msg.dof, msg.iterations = f.chi2, f.dof, f.iterations
    msg.status = STATUS_ENUMS[f.status]
    # the arrays merged in as packed bytes, each at once rather than a Python float at a time
    # (a Subscribe answer's message ~30 % faster, docs/benchmarks/world.md)
    wire = [packed(4, f.covariance), packed(12, f.distances), packed(13, f.nis),
            packed(14, f.tested, "u1"), packed(15, f.residuals)]
    for s in f.sources:
        msg.sources.add(name=s.name, count=s.count, rejected=s.rejected, nis_mean=s.nis_mean,
                        low=s.low, high=s.high, verdict=int(s.verdict))
    for d in f.dropped:
        msg.dropped.add(index=d.index, source=d.source, age=d.age, reason=d.reason)
    if f.twist is not None:
        assert f.twist_covariance is not None      # fusion sets the two together
        wire += [packed(22, f.twist), packed(23, f.twist_covariance)]
    msg.extrapolation = f.extrapolation
    for a in f.latencies:
        msg.latencies.add(source=a.name, configured=a.configured, prior_sigma=a.prior_sigma,
                          value=a.value, sigma=a.sigma)
    msg.MergeFromString(b"".join(wire))
    return msg


def _dropped(d, max_skew: float | None) -> fusion.Dropped:
    """A ``FusedPose.dropped`` entry: for skew, or (another reason) with the server's words."""
    skew = fusion.Dropped(d.index, d.source, d.age, max_skew or 0.0)
    if d.reason == skew.reason:
        return skew
    who = skew.reason[:len(skew.reason) - len(skew.reason.split(": ", 1)[-1])]
    why = d.reason[len(who):] if d.reason.startswith(who) else d.reason
    return fusion.Dropped(d.index, d.source, d.age, max_skew or 0.0, why)


def fused_from_msg(msg, probability: float = DEFAULT_PROBABILITY,
                   max_skew: float | None = None) -> fusion.Fused:
    """A ``FusedPose`` back into the :class:`fusion.Fused` it was made from (client side);
    ``probability`` and ``max_skew`` are the request's (the gate of each rejection, the bound
    of each drop)."""
    nis = np.array(msg.nis, dtype=np.float64)
    gate = math.sqrt(fusion.chi2_quantile(probability, fusion.DOF))
    rejected = [fusion.Rejection(int(i), source, math.sqrt(nis[i]), gate, probability)
                for i, source in zip(msg.rejected, msg.rejected_sources)]

    def frozen(a):
        a = np.ascontiguousarray(a)
        a.flags.writeable = False
        return a

    return fusion.Fused(
        status=STATUS_NAMES.get(msg.status, fusion.Status.CONVERGED),
        mean=frozen(pose_to_dq(msg.pose)),
        covariance=frozen(np.array(msg.covariance, dtype=np.float64).reshape(6, 6)),
        residuals=frozen(np.array(msg.residuals, dtype=np.float64).reshape(-1, 6)),
        distances=frozen(np.array(msg.distances, dtype=np.float64)),
        nis=frozen(nis),
        tested=frozen(np.array(msg.tested, dtype=bool)),
        inliers=frozen(np.array(msg.inliers, dtype=np.int64)),
        rejected=tuple(rejected),
        chi2=msg.chi2, dof=msg.dof, iterations=msg.iterations,
        sources=tuple(fusion.SourceStats(s.name, s.count, s.rejected, s.nis_mean, s.low, s.high,
                                         fusion.Verdict(s.verdict)) for s in msg.sources),
        time=msg.time,
        twist=frozen(np.array(msg.twist, dtype=np.float64)) if msg.twist else None,
        twist_covariance=frozen(np.array(msg.twist_covariance, dtype=np.float64).reshape(6, 6))
        if msg.twist else None,
        extrapolation=msg.extrapolation,
        dropped=tuple(_dropped(d, max_skew) for d in msg.dropped),
        latencies=tuple(fusion.Latency(a.source, a.configured, a.prior_sigma, a.value, a.sigma)
                        for a in msg.latencies))


# ---- a FuseRequest as fusion.fuse's arguments, errors named by field ---------------------------

# The domain's per-measurement arguments, as fields of a Measurement.
_MEASUREMENT_FIELDS = {"poses": "pose", "covariances": "covariance", "times": "time",
                       "names": "source"}
_OPTION_FIELDS = ("probability", "time", "max_skew", "max_extrapolation", "window",
                  "twist_covariance", "acceleration_psd")


def options_error(e: ValueError, field: str) -> FieldError:
    """The domain's ``ValueError`` about an option, naming the field under ``field``."""
    return rename(e, {"sources": f"{field}.sources{{}}",
                      **{name: f"{field}.{name}" for name in _OPTION_FIELDS}})


def _domain_error(e: ValueError, index: np.ndarray, field: str, options: str) -> FieldError:
    """The domain's ``ValueError`` about row ``k`` of the arrays it was given, naming the
    message's measurement ``index[k]``; one about all of them (the fit's information), naming
    ``field``; one about the options, naming the option (read from the error's fields,
    :meth:`FieldError.of`)."""
    f = FieldError.of(e)
    if f.field in _MEASUREMENT_FIELDS and f.index is not None:
        at = f"{field}[{int(index[f.index])}].{_MEASUREMENT_FIELDS[f.field]}"
        return rename(f, {f.field: at})
    if f.path() == "covariances":     # the fit of them all, not one covariance
        return FieldError(field, f"{f.text} (the measurements' covariances and times, with the "
                                 f"options' priors, leave the pose, twist or latencies "
                                 f"undetermined)")
    return options_error(f, options)


def unknown_sources(m: Measurements, options: Options, field: str) -> list:
    """Rows of ``m`` whose source the options do not list (when they list any), each with the
    error naming it: a misspelt name would otherwise silently lose its frames."""
    if not options.sources:
        return []
    known = {s.name for s in options.sources}
    listed = ", ".join(s.name for s in options.sources)
    return [(k, FieldError(f"{field}[{int(m.index[k])}].source: {quoted(m.sources[k])} is not "
                           f"among options.sources ({listed})"))
            for k in range(len(m.index)) if m.sources[k] not in known]


class FuseArgs(NamedTuple):
    """A ``FuseRequest`` as :func:`dqpose.fusion.fuse`'s arguments (:meth:`kwargs`), of one
    body."""
    measurements: Measurements
    options: Options

    @property
    def body(self) -> str:
        return self.measurements.bodies[0]

    def kwargs(self) -> dict:
        m, options = self.measurements, self.options
        return dict(poses=m.poses, covariances=m.covariances, names=m.sources, times=m.times,
                    time=options.time or None, **options.fuse_kwargs())

    def error(self, e: ValueError) -> FieldError:
        """What :func:`dqpose.fusion.fuse` raised for these arguments, named by field."""
        return field_named(_domain_error(e, self.measurements.index, "measurements", "options"),
                           ("measurements", "options"), "measurements")


def fuse_from_msg(request, bounds: limits.Limits = limits.DEFAULT,
                  max_poses: int = DEFAULT_MAX_POSES) -> FuseArgs:
    """A ``FuseRequest`` as :class:`FuseArgs`, checked as Fuse checks it within ``bounds`` and
    ``max_poses`` (the server's; the defaults are ``dqpose serve``'s): one body, no window, times
    within ``max_time``, every source listed (when the options list any), a fit within the
    robust and the correlated fits' limits."""
    n = len(request.measurements)
    check_count("measurements", n, max_poses, "measurements", empty=True)
    options = options_from_msg(request.options)
    _check_fit_size("measurements", n, options, bounds)
    m = measurements_to_arrays(request.measurements)
    if n:
        check_name(m.bodies[0], "measurements[0].body", empty=True)    # Fuse's may be ""
    for k, body in enumerate(m.bodies):
        if body != m.bodies[0]:
            raise FieldError(f"measurements[{k}].body: {quoted(body)} differs from "
                             f"measurements[0].body {quoted(m.bodies[0])} (Fuse fuses one "
                             f"body; StreamFuse takes many)")
    if options.window:
        raise FieldError("options.window: Fuse keeps no window (StreamFuse does); leave it 0")
    _check_times(m.times, m.index, "measurements", options, bounds)
    unknown = unknown_sources(m, options, "measurements")
    if unknown:
        raise unknown[0][1]
    return FuseArgs(m, options)


def fused_of(request, bounds: limits.Limits = limits.DEFAULT,
             max_poses: int = DEFAULT_MAX_POSES) -> tuple[fusion.Fused, str]:
    """:func:`dqpose.fusion.fuse` of a ``FuseRequest`` and its body, the request checked
    (:func:`fuse_from_msg`) and the domain's errors named by field: Fuse's fit."""
    args = fuse_from_msg(request, bounds, max_poses)
    try:
        fused = fusion.fuse(**args.kwargs())
    except ValueError as e:
        raise args.error(e) from None
    assert fused.time is not None       # the measurements have times (kwargs)
    return fused, args.body


def fused_pose(request, bounds: limits.Limits = limits.DEFAULT,
               max_poses: int = DEFAULT_MAX_POSES) -> fpb.FusedPose:
    """:func:`fused_of` as its ``FusedPose`` message: what ``dqpose fuse --local`` computes in
    process (the server writes the same message's bytes in C)."""
    fused, body = fused_of(request, bounds, max_poses)
    assert fused.time is not None       # the measurements have times (fused_of)
    return fused_to_msg(fused, body, fused.time)


def _check_times(times: np.ndarray, index: np.ndarray, field: str, options: Options,
                 bounds: limits.Limits) -> None:
    """Every time within ``+-max_time``: beyond it a time has no microseconds left, and the
    fit's differences of times lose all meaning (1e308 made its information singular)."""
    bound = bounds.max_time
    far = np.flatnonzero(np.abs(times) > bound)
    if len(far):
        k = int(far[0])
        raise limits.beyond_time(f"{field}[{int(index[k])}].time", float(times[k]), bounds)
    if abs(options.time) > bound:
        raise limits.beyond_time("options.time", options.time, bounds)


def _check_fit_size(field: str, n: int, options: Options, bounds: limits.Limits) -> None:
    """``n`` measurements in one fit with ``options``: within the robust and the correlated
    fits' limits, or :class:`limits.OverLimit` naming the one passed."""
    if options.robust and n > bounds.max_robust:
        raise limits.over(field, f"{n} measurements in one robust fit (options.robust)",
                          bounds, "max_robust")
    if (options.acceleration_psd is not None and options.acceleration_psd.any()
            and n > bounds.max_correlated):
        raise limits.over(field, f"{n} measurements in one fit with "
                                 f"options.acceleration_psd", bounds, "max_correlated")
