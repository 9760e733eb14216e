"""Live streams: :class:`Tracker` keeps a sliding window of measurements per body (many bodies,
keyed by name) and fuses a body's window at a time with :func:`~dqpose.fusion.fuse`; the stream's
bounds are a :class:`~dqpose.fusion.bounds.TrackerBounds` (a server's filled from its
:class:`dqpose.limits.Limits`), its refusals :class:`~dqpose.errors.WorldError` s.
"""
from __future__ import annotations

import dataclasses
import math
from typing import TYPE_CHECKING, Iterable, Mapping, NamedTuple, Optional, Sequence

import numpy as np

from dqpose import dq
from dqpose import limits as _limits
from dqpose._dqcore import REFUSED_FLOOR, REFUSED_JUMP, REFUSED_TIME
from dqpose.errors import FieldError, WorldError
from dqpose.fusion.alignment import (
    DEFAULT_MAX_EXTRAPOLATION,
    joint_start,
    pose_in_time,
    pose_over_time,
)
from dqpose.fusion.api import (
    Checked,
    fuse,
    fuse_joint_rows,
    fuse_static_rows,
    fuse_world_rows,
)
from dqpose.fusion.bounds import TrackerBounds
from dqpose.fusion.chi2 import DEFAULT_PROBABILITY, chi2_quantile
from dqpose.fusion.measurements import Measurement, Rows, rows_of
from dqpose.fusion.results import DOF, Fused
from dqpose.fusion.sources import Source, source_table, to_world
from dqpose.fusion.store import Store
from dqpose.fusion.validation import (
    check_rows,
    checked_seconds,
    finite_shape,
    named_rows,
)

if TYPE_CHECKING:
    from dqpose.riders import Riders


class Window(NamedTuple):
    """A body's sliding window as arrays, in arrival order (the order of the indices of its
    :meth:`Tracker.estimate`): per measurement the caller's number (``ids``), source, stamp,
    the time it was taken (stamp minus the source's latency), pose (as given: checked to be a
    unit rigid motion, normalised by :func:`fuse`) and covariance (symmetrised)."""
    ids: np.ndarray
    sources: tuple[str, ...]
    times: np.ndarray
    taken: np.ndarray
    poses: np.ndarray
    covariances: np.ndarray


class Tracker:
    """Sliding-window state of many bodies, keyed by name, for a live stream of measurements.

    Each body keeps its measurements taken (stamp minus the source's latency) within ``window``
    seconds of its newest; one taken further back than that is refused, naming it.
    :meth:`ingest` takes measurements of any bodies (arrays or objects), checks them together in
    NumPy and keeps every valid one, returning the errors of the others (a live stream goes on
    past a bad measurement), or all or none. :meth:`estimate` fuses a body's window at a time
    with :func:`fuse` (its keyword options are those given here).
    Bodies are independent: nothing of one enters another's estimate.

    ``bounds`` (:class:`~dqpose.fusion.bounds.TrackerBounds`; None: unbounded) bound what a
    stream keeps: a body's window holds its last ``max_window`` measurements (``max_robust`` when
    robust, ``max_correlated`` with an ``acceleration_psd``), the stream ``max_rows`` in all
    (more are refused), a time beyond ``+-max_time`` is
    refused, and a measurement taken more than ``max_time_jump`` after its body's newest is
    refused without moving the body, unless the body's next such measurement confirms the jump
    (a clock that really moved, a body seen again after a pause): one stray stamp never poisons
    a body. Rows may name their ``origin`` (a World's producer): a jump is confirmed by another
    origin's measurement near it, or by its own while no other origin fed the body within
    ``max_time_jump`` of its newest (a body seen again after a pause by the one camera that sees
    it), so one producer's clock never takes a body away from the others feeding it. The rules
    and the store's rows are the C's (service/csrc/store.h ``dq_store_ingest``).
    """

    def __init__(self, window: float, *, sources: Optional[Iterable[Source]] = None,
                 robust: bool = False, probability: float = DEFAULT_PROBABILITY,
                 max_skew: Optional[float] = None,
                 max_extrapolation: Optional[float] = DEFAULT_MAX_EXTRAPOLATION,
                 twist_covariance=None, acceleration_psd=None, tol: float = 1e-12,
                 max_iter: int = 100, bounds: Optional[TrackerBounds] = None):
        self.window = checked_seconds(window, "window", "positive")
        self.bounds = bounds
        self.sources = tuple(sources or ())
        self.table = source_table(self.sources)      # name -> Source, read by the world's modules
        # the options' checks are fuse's: one fusion of a placeholder runs them now, not later
        # (its parents a world's, which fuse refuses)
        fuse(dq.identity((1,)), times=[0.0],
             sources=[dataclasses.replace(s, parent="") for s in self.table.values()],
             robust=robust, probability=probability, max_skew=max_skew,
             max_extrapolation=max_extrapolation, twist_covariance=twist_covariance,
             acceleration_psd=acceleration_psd, tol=tol, max_iter=max_iter)
        probability = float(probability)
        # every fit's options (fusion.api.Checked), the checked ones of the arguments above
        self.options = Checked(self.table, robust, probability,
                                 chi2_quantile(probability, DOF), dq.as_tol(tol),
                                 dq.as_iter(max_iter), max_skew, max_extrapolation,
                                 twist_covariance, acceleration_psd)
        self.store = Store(world_covs=any(src.body_offset is not None
                                            for src in self.table.values()))
        # bodies and sources as small integers in the store: a body's newest taken time, a
        # source's configured latency
        self.body_codes: dict[str, int] = {}
        self._active: dict[str, None] = {}        # bodies with measurements, in order
        self._newest = np.full(16, -math.inf)
        # per body code and source code: the newest measurement of that source taken
        self._by_source = np.full((16, 4), -math.inf)
        self._codes: dict[str, int] = {}
        self.source_names: list[str] = []
        self.latencies = np.empty(0)
        # per source code: its extrinsic and latency exact (no extrinsic_covariance, no
        # latency_sigma), for estimate's fit="pose"
        self._exact = np.empty(0, dtype=bool)
        self._all_exact = all(src.exact for src in self.table.values())
        # a World's riders (dqpose.riders.Riders: rows composed with their parents' poses when
        # fitted) and, per source code, whether it is one
        self.riders: Optional[Riders] = None
        self.riding = np.empty(0, dtype=bool)
        self._count = 0            # measurements offered so far: the default ids
        # the bodies of the last ingest's measurements taken in, once each, in order
        self.touched: tuple = ()
        # rows whose source has frames are brought to the world frame in NumPy (_in_world), the
        # others by the store's C (unit poses, covariances as they are)
        self._framed = any(src.body_offset is not None or src.extrinsic is not None
                           for src in self.table.values())
        self.cap = None            # measurements a body's window holds (None: all)
        if bounds is not None:
            self.cap = bounds.cap(robust, bool(acceleration_psd is not None
                                               and np.any(acceleration_psd)))
        # the store's C check's rules (window, cap, max_time, max_time_jump, max_rows; < 0: none)
        b = bounds
        self._rules = (self.window, -1 if self.cap is None else self.cap,
                       math.inf if b is None else b.max_time,
                       math.inf if b is None else b.max_time_jump, -1 if b is None else b.max_rows)

    @property
    def exact(self) -> bool:
        """Whether every configured source's extrinsic and latency are exact (no
        ``extrinsic_covariance``, no ``latency_sigma``): then no two bodies share an error."""
        return self._all_exact

    @property
    def bodies(self) -> tuple[str, ...]:
        return tuple(self._active)

    @property
    def held(self) -> Mapping[str, None]:
        """The bodies with measurements, in the order they came (a view: read, never written)."""
        return self._active

    def version(self, body: str) -> int:
        """How many requests (calls of :meth:`ingest`) brought ``body``
        measurements (0: none): a body's answers change only when this does."""
        code = self.body_codes.get(body)
        return 0 if code is None else self.store.index.version(code)

    def window_of(self, body: str) -> Window:
        """``body``'s window as arrays, in the order of its :meth:`estimate`'s indices."""
        s, rows = self.store, self._rows(body)
        return Window(s.ids[rows], tuple(self.source_names[c] for c in s.codes[rows]),
                      s.times[rows], s.taken[rows], s.poses[rows], s.covs[rows])

    def measurements(self, body: str) -> tuple[Measurement, ...]:
        """``body``'s window, in the order of the indices in its :meth:`estimate`."""
        w = self.window_of(body)
        return tuple(Measurement(s, body, float(t), p, c)
                     for s, t, p, c in zip(w.sources, w.times, w.poses, w.covariances))

    def newest(self, body: str) -> float:
        """When ``body``'s newest measurement was taken."""
        return float(self._newest[self._code_of(body)])

    def by_source(self, body: str) -> dict[str, float]:
        """When ``body``'s newest measurement of each source that fed it was taken (those whose
        measurements it holds or held)."""
        row = self._by_source[self._code_of(body)].tolist()
        names = self.source_names
        return {names[c]: t for c, t in enumerate(row) if t != -math.inf}

    def newest_of(self, bodies: Iterable[str]) -> list[float]:
        """:meth:`newest` of each of ``bodies`` (which have measurements), in one go."""
        codes = self.body_codes
        return self._newest[[codes[b] for b in bodies]].tolist()

    def count(self, body: str) -> int:
        """How many measurements ``body``'s window holds."""
        return len(self._rows(body))

    def capped(self, body: str, within: Optional[float] = None) -> bool:
        """Whether ``body``'s window (its rows taken ``within`` its newest; default
        :attr:`window`) leaves measurements out for its ``cap``."""
        if self.cap is None:
            return False
        s = self.store
        return len(s.rows(self._code_of(body), self._newest,
                          self.window if within is None else within)) > self.cap

    def oldest(self, body: str) -> float:
        """When the oldest measurement in ``body``'s window was taken."""
        return float(self.store.taken[self._rows(body)].min())

    def spans(self, bodies: Sequence[str], recent: float) -> tuple:
        """:meth:`oldest` and :meth:`newest` of each of ``bodies`` (which have measurements),
        how many of its window's rows were taken within ``recent`` s before its newest, and the
        names of the sources of :meth:`by_source`, in one pass over the live rows (C: a list of
        every body; one body's looks cost ~13 us)."""
        s = self.store
        codes = np.fromiter(map(self.body_codes.__getitem__, bodies), np.int64, len(bodies))
        oldest, near = s.spans(self._newest, self.window, self.cap, recent)
        # the sources' sets by pattern: few patterns among many bodies
        seen = self._by_source[codes] != -math.inf
        names, fed = self.source_names, []
        if len(codes):
            if seen.shape[1] <= 62:     # each row's pattern as one integer
                _, first, which = np.unique(seen @ (1 << np.arange(seen.shape[1])),
                                            return_index=True, return_inverse=True)
            else:
                _, first, which = np.unique(seen, axis=0, return_index=True,
                                            return_inverse=True)
            named = [tuple(names[c] for c in np.flatnonzero(seen[i])) for i in first.tolist()]
            fed = [named[k] for k in which.ravel().tolist()]
        return oldest[codes], self._newest[codes], near[codes], fed

    def remove(self, body: str) -> None:
        b = self._code_of(body)
        s = self.store
        s.keep(s.body[:s.n] != b)
        self._newest[b] = -math.inf
        self._by_source[b] = -math.inf
        s.index.forget(b)
        del self._active[body]

    def ingest(self, rows: "Rows | Sequence[Measurement]", *, ids=None, origin=None,
               checked=None, all_or_none: bool = False) -> list[tuple[int, WorldError]]:
        """Add measurements of any bodies: :class:`Rows` (arrays: ``times`` ``(n,)`` stamps,
        ``poses`` ``(n, 8)`` ``T_frame_body``, ``covariances`` ``(n, 6, 6)``, None: identity) or
        :class:`Measurement` s. ``ids`` ``(n,)`` the caller's numbers, which :meth:`window_of`
        returns (default: counting every measurement offered to this tracker); ``origin`` who
        sent them (the class's docstring). Every valid measurement is kept; returned are
        ``(k, WorldError)`` for the others, each about ``measurements[k]`` and the problem (a
        name that is not one, a time that is not finite, a pose that is not a unit rigid motion,
        a covariance that is not symmetric positive definite, a time taken further back than the
        window, or beyond the bounds). ``all_or_none``: none kept if one is refused, the first
        refusal raised. ``checked`` ``(n,)``: the rows a decoder checked by these rules
        (service/csrc/wire.c, for StreamFuse and World.Publish), 0 a row taken in without
        checking it again, else the row named by this tracker's own check of it alone; the same
        answers. Arrays of the wrong shape are a ``ValueError`` for the call."""
        bad: dict[int, WorldError] = {}
        if not isinstance(rows, Rows):
            rows, bad = rows_of(rows)
            if bad and all_or_none:
                raise min(bad.items())[1]
        if checked is not None and not bad and not all_or_none:
            return self._ingest_checked(rows, ids, np.asarray(checked), origin)
        got = self._ingest(rows, ids, all_or_none, origin, bad)
        if all_or_none and got:
            raise got[0][1]
        return got

    def estimate(self, body: Optional[str] = None, time: Optional[float] = None, *,
                 rows: Optional[np.ndarray] = None, within: Optional[float] = None,
                 nis: bool = True, joint: bool = True, fit: str = "full", ids: bool = False):
        """``body``'s pose at ``time`` (default: its newest measurement's) from its window
        (``within``: its measurements taken within that many seconds of ``time``, of the newest
        when None), or from ``rows`` (:meth:`rows_ending`'s), a :class:`Fused`; with ``ids``,
        and the ids of the measurements it fused (:meth:`window_of`'s). Without ``nis`` (an
        answer that needs the pose and its covariance only) a fit over time that is not robust
        leaves out the leave-one-out NIS (``nis`` zeros, ``tested`` all False), everything else
        the same to the last bit; without ``joint``, where :meth:`joint` may start the body.
        ``fit``: ``"full"``; ``"static"`` the one-instant fit (a body that does not move: no
        twist, the times left out; a rider's rows composed with its parent's pose at each row's
        time); ``"pose"`` only ``(mean, covariance)`` of the full fit without ``nis``, bit for
        bit (a Lookup of a body); ``"start"`` where the body starts in :meth:`joint` at
        ``time``."""
        if rows is None:
            if body is None:
                raise FieldError("body", "give a body or its rows")
            rows = self._rows_near(body, time, within)
        if fit == "pose":
            assert time is not None
            return self._pose(rows, time)
        if fit == "start":
            assert time is not None
            return self._start(rows, time)
        if fit == "static":
            got = self._static(rows)
        elif fit == "full":
            got = self._fit(rows, time, nis, joint)
        else:
            raise FieldError("fit", f"expected 'full', 'static', 'pose' or 'start', got {fit!r}")
        return got if ids else got[0]

    def _fit(self, rows: np.ndarray, time: Optional[float], nis: bool,
             joint: bool) -> tuple[Fused, np.ndarray]:
        if self.riders is not None:     # a World's sources riding on its bodies
            got = self.riders.fit(rows, time, nis, joint)
            if got is not None:
                return got
        s = self.store
        # the rows were checked by fuse's rules when they came in, and brought into the world
        # frame (_in_world)
        return fuse_world_rows(*s.world(rows), self.row_sources(rows), s.times[rows],
                                time, self.options, nis, joint), s.ids[rows]

    def _pose(self, rows: np.ndarray, time: float) -> tuple[np.ndarray, np.ndarray]:
        """The constant-twist fit straight from the rows where it applies (``pose_in_time``),
        else any fit over time that is not robust (``pose_over_time``), else the full fit's."""
        s = self.store
        codes = s.codes[rows]
        got = None
        if self.riders is not None and self.riding[codes].any():
            f = self._fit(rows, time, False, True)[0]
            return f.mean, f.covariance
        if self._all_exact or self._exact[codes].all():
            # taken was stamp less latency when the rows came in: the same bits as fuse's
            got = pose_in_time(*s.world(rows), self.latencies[codes], s.times[rows],
                                s.taken[rows], time, self.options)
        if got is None:
            got = pose_over_time(*s.world(rows), self.row_sources(rows), s.times[rows], time,
                                  self.options)
        if got is None:
            f = self._fit(rows, time, False, True)[0]
            got = f.mean, f.covariance
        return got

    def _start(self, rows: np.ndarray, time: float):
        """The constant-twist fit (where its own joint fit starts) without the rest of an
        answer where that is the fit (``joint_start``), else the full fit's (``nis`` and
        ``joint`` False)."""
        s = self.store
        got = joint_start(*s.world(rows), self.row_sources(rows), s.times[rows], time,
                           self.options)
        return got if got is not None else self._fit(rows, time, False, False)[0]

    def _static(self, rows: np.ndarray) -> tuple[Fused, np.ndarray]:
        if self.riders is not None:
            got = self.riders.fit(rows, None, True, True, static=True)
            if got is not None:
                return got
        s = self.store
        return fuse_static_rows(*s.world(rows), self.row_sources(rows), self.options), \
            s.ids[rows]
    def row_sources(self, rows: np.ndarray) -> tuple[str, ...]:
        """Each row's source name, as the fits take them."""
        names = self.source_names
        return tuple([names[c] for c in self.store.codes[rows].tolist()])

    def rows_ending(self, body: str, end: float, window: float) -> np.ndarray:
        """``body``'s rows taken in ``[end - window, end]`` (for :meth:`estimate`), in
        arrival order, the last :attr:`cap` of them, among the rows of its window (:meth:`_rows`:
        the last :attr:`cap` of those too). Looked for from the first row whose running maximum
        of taken reaches ``end - window`` (:meth:`Store.after`): the rows of that window and
        those that came after them late, not the body's whole window, unless more than
        :attr:`cap` of its window's rows are among them (then its cap may leave some out)."""
        b, s, cap = self._code_of(body), self.store, self.cap
        lo, floor = end - window, self._newest[b] - self.window
        rows = s.after(b, lo) if lo > floor else None
        if rows is None or (cap is not None and len(rows) > cap
                            and np.count_nonzero(s.taken[rows] >= floor) > cap):
            rows = self._rows(body)
        taken = s.taken[rows]
        mine = rows[(taken >= lo) & (taken <= end)]
        return mine if cap is None or len(mine) <= cap else mine[len(mine) - cap:]

    def taken_of(self, rows: np.ndarray) -> np.ndarray:
        """When ``rows`` were taken."""
        return self.store.taken[rows]

    def sources_of(self, rows: np.ndarray) -> set[str]:
        """The sources of ``rows``."""
        return {self.source_names[c] for c in np.unique(self.store.codes[rows]).tolist()}

    def has(self, body: str) -> bool:
        """Whether ``body`` has measurements."""
        return body in self._active

    def joint(self, rows: Sequence[np.ndarray], fits: Sequence,
              time: Optional[float] = None) -> tuple[list, np.ndarray]:
        """Bodies fitted together from their ``rows`` (each body's, :meth:`rows_ending`'s) with
        one error per uncertain extrinsic their sources share (:mod:`dqpose.fusion.extrinsics`),
        each from its own :meth:`estimate` ``fits`` (its ``fit="start"``'s: their inliers,
        their start): the poses and the joint covariance ``(6k, 6k)`` of their right perturbations,
        cross-covariances included."""
        s = self.store
        return fuse_joint_rows([(*s.world(r), self.row_sources(r), s.times[r]) for r in rows],
                                fits, time, self.options)

    def _rows_near(self, body: str, time: Optional[float], within: Optional[float]):
        rows = self._rows(body)
        if within is None:
            return rows
        t = self.newest(body) if time is None else time
        return rows[np.abs(self.store.taken[rows] - t) <= within]

    def _code_of(self, body: str) -> int:
        if body not in self._active:
            raise FieldError("body", f"no measurements of {body!r}")
        return self.body_codes[body]

    def _rows(self, body: str) -> np.ndarray:
        return self.store.rows(self._code_of(body), self._newest, self.window, self.cap)

    def _source_code(self, source: str) -> int:
        code = self._codes.get(source)
        if code is None:
            code = self._codes[source] = len(self.source_names)
            self.source_names.append(source)
            src = self.table.get(source)
            self.latencies = np.append(self.latencies, src.latency if src is not None else 0.0)
            self._exact = np.append(self._exact, src is None or src.exact)
            self.riding = np.append(self.riding, src is not None and bool(src.parent))
            if code >= self._by_source.shape[1]:
                self._by_source = np.pad(self._by_source, ((0, 0), (0, code + 1)),
                                         constant_values=-math.inf)
        return code

    def _body_code(self, body: str) -> int:
        code = self.body_codes.get(body)
        if code is None:
            code = self.body_codes[body] = len(self.body_codes)
            if code >= len(self._newest):
                self._newest = np.concatenate([self._newest, np.full(len(self._newest),
                                                                     -math.inf)])
                self._by_source = np.pad(self._by_source, ((0, len(self._newest)
                                                            - len(self._by_source)), (0, 0)),
                                         constant_values=-math.inf)
        return code

    def _ingest(self, rows: "Rows", ids, all_or_none: bool, origin, bad: dict):
        """The rows checked here (:func:`check_rows`; ``bad`` refused already), then admitted."""
        bodies, sources = rows.bodies, rows.sources
        n = len(bodies)
        if len(sources) != n:
            raise FieldError("sources", f"expected {n} names, got {len(sources)}")
        times = finite_shape(rows.times, "times", (n,))
        poses = finite_shape(rows.poses, "poses", (n, 8))
        covs = (np.broadcast_to(np.eye(DOF), (n, DOF, DOF)) if rows.covariances is None
                else finite_shape(rows.covariances, "covariances", (n, DOF, DOF)))
        ids = np.arange(self._count, self._count + n) if ids is None else np.asarray(ids, np.int64)
        if ids.shape != (n,):
            raise FieldError("ids", f"expected shape {(n,)}, got {ids.shape}")
        ok, errors, covs = check_rows(bodies, sources, times, poses, covs)
        if bad:
            errors.update(bad)
            ok[list(bad)] = False
        return self._admit(bodies, sources, times, poses, covs, ids, ok, errors, n, all_or_none,
                           origin)

    @staticmethod
    def refusals(bodies, sources, times, poses, covariances) -> list[tuple[int, WorldError]]:
        """What :meth:`ingest` would refuse of these measurements (arrays as it takes them) by
        the checks that need no state (all but the window), each ``(k, WorldError)`` about
        ``measurements[k]``."""
        return sorted(check_rows(bodies, sources, np.asarray(times, np.float64),
                                  np.asarray(poses, np.float64),
                                  np.asarray(covariances, np.float64))[1].items())

    def _ingest_checked(self, rows: "Rows", ids, codes: np.ndarray,
                        origin) -> list[tuple[int, WorldError]]:
        """:meth:`ingest` of rows a decoder checked (``codes``), without checking the good rows
        again (``times`` finite, ``poses`` unit as ``dq.from_pose`` makes them, ``covariances``
        the symmetric part of symmetric positive definite ones) but for the window. The names,
        which a decoder passes as strings, are checked here."""
        bodies, sources, times, poses, covariances = rows
        assert covariances is not None      # a decoder's: every row has one
        n = len(bodies)
        if not np.count_nonzero(codes):     # the common case: every row taken in, names known
            got = self._admit(bodies, sources, times, poses, covariances, ids, None, {}, n, False,
                              origin, new_names=False)
            if got is not None:
                return got
        if isinstance(ids, int):
            ids = ids + np.arange(n)
        # a name coded already was checked when it came first (here or by refusals)
        named = named_rows(bodies, sources, self.body_codes, self._codes)
        if named:       # refused for a name: then named by the check of the row alone
            codes = codes.astype(np.int64)
            codes[named] = -1
        coded = np.flatnonzero(codes).tolist()
        if not coded:           # the common case: every row taken in
            return self._admit(bodies, sources, times, poses, covariances, ids, np.ones(n, bool),
                               {}, n, False, origin)
        refused = [(k, self.refusals(
            bodies[k:k + 1], sources[k:k + 1], times[k:k + 1], poses[k:k + 1],
            covariances[k:k + 1])[0][1].at(k)) for k in coded]
        good = np.flatnonzero(codes == 0)
        use = good.tolist()
        refused += [(use[j], e.at(use[j])) for j, e in self._admit(
            [bodies[k] for k in use], [sources[k] for k in use], times[good], poses[good],
            covariances[good], np.asarray(ids)[good], np.ones(len(use), bool), {}, n, False,
            origin)]
        return sorted(refused, key=lambda x: x[0])
    def _admit(self, bodies, sources, times, poses, covs, ids, ok, errors, offered: int,
               all_or_none: bool, origin=None, new_names: bool = True):
        """Checked measurements (``ok``; ``errors`` those refused so far) into the windows in one
        C call (service/csrc/store.h ``dq_store_ingest``: the limits' time checks, the jump rule,
        the window floor, the room, then the store), its refusals named here (:meth:`_refusal`).
        A body or source new to the tracker is coded first (unless not ``new_names``: then None,
        nothing done)."""
        s = self.store
        s.reserve(len(bodies), self._newest, self.window, self.cap)
        wposes = wcovs = None
        if self._framed and (ok is None or ok.any()):
            wposes, wcovs = self._in_world(sources, poses, covs,
                                           np.ones(len(bodies), bool) if ok is None else ok)
        rules = self._rules + (None if origin is None else hash(origin), all_or_none)
        got = s.index.ingest(s, self._newest, self._by_source, self.latencies, bodies,
                              self.body_codes, sources, self._codes, ids, times, poses, covs, ok,
                              wposes, wcovs, *rules)
        if got is None:         # a name new to the tracker: coded, sources first, in row order
            if not new_names:
                return None
            use = [True] * len(bodies) if ok is None else ok.tolist()
            for u, src in zip(use, sources):
                if u:
                    self._source_code(src)
            for u, body in zip(use, bodies):
                if u:
                    self._body_code(body)
            got = s.index.ingest(s, self._newest, self._by_source, self.latencies, bodies,
                                  self.body_codes, sources, self._codes, ids, times, poses, covs,
                                  ok, wposes, wcovs, *rules)
        refused, fresh, self.touched = got
        for k, code, x, y in refused:
            errors[k] = self._refusal(k, code, x, y, bodies[k], sources[k], times[k])
        if all_or_none and errors:
            self.touched = ()
            return [min(errors.items())]
        self._count += offered
        if fresh:           # a body without measurements got some
            for body in self.touched:
                self._active.setdefault(body, None)
        return sorted(errors.items()) if errors else []

    def _refusal(self, k: int, code: int, x: float, y: float, body, source,
                 time) -> WorldError:
        """Row ``k`` refused by the C check ``code`` (store.h's ``DQ_REFUSED_*``) with its
        numbers ``x``, ``y``, as its text names it."""
        about = f"body {body!r}, source {source!r}, time {float(time)!r}"
        if code == REFUSED_TIME:
            return WorldError(k, "time", _limits.beyond_time_text(x, y), "max_time")
        if code == REFUSED_JUMP:
            who = "" if y else " from another producer"
            assert self.bounds is not None      # refused only by a tracker with bounds
            return WorldError(k, "", _limits.over_text(
                f"{about}: taken {x:.6g} s after the newest measurement of the body, so not used "
                f"(a second measurement near it{who} would confirm the jump)", "max_time_jump",
                self.bounds.max_time_jump), "max_time_jump")
        if code == REFUSED_FLOOR:
            return WorldError(k, "", f"taken at {x!r}, {y - x:.6g} s before the newest "
                                     f"measurement of the body, beyond the window "
                                     f"{self.window:g} s", about=about)
        return WorldError(k, "", _limits.over_text(
            f"the stream's windows hold {int(x)} measurements", "max_stream_measurements",
            int(y)), "max_stream_measurements")

    def _in_world(self, sources, poses, covs, ok) -> tuple[np.ndarray, Optional[np.ndarray]]:
        """The rows ``ok`` in the world frame as :func:`~dqpose.fusion.fuse` brings them there
        (the same operations on the same rows, so the same bits), for the store to keep: a fit
        then reads them as they are (the covariances only when a body offset moves them)."""
        idx = None if ok.all() else np.flatnonzero(ok)
        if idx is not None:
            sources, poses, covs = [sources[k] for k in idx.tolist()], poses[idx], covs[idx]
        wposes, wcovs = to_world(dq.normalize(poses), covs, tuple(sources), self.table)
        if idx is not None:
            full = np.zeros((len(ok), 8))
            full[idx] = wposes
            wposes = full
            fullc = np.zeros((len(ok), DOF, DOF))
            fullc[idx] = wcovs
            wcovs = fullc
        return wposes, wcovs if "wcovs" in self.store.arrays else None
