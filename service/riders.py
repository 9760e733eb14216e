"""Sources riding on bodies (``Source.parent``): a camera on an arm's tool, on a mobile base.

A rider's measurement is kept as every measurement is, in its source's frame composed with the
extrinsic and body offset (``E · Z · O``, :mod:`dqpose.fusion.sources`), which for a rider is its
parent's frame; it is brought to the world when a fit takes it, never at ingest, so a replay
stays a function of arrival order: row i becomes ``T_world_P(t_i) · E · Z_i · O`` with the
parent P's pose at the row's taken time ``t_i`` (P's own fit, :meth:`World.pose_only`). A row
whose time P is not known at is left out of that fit and listed among its dropped measurements
(a :class:`~dqpose.fusion.Dropped` with its ``why``), after the rows it fitted.

Covariance model. With ``T_world_P · Exp(δP) · E · Exp(δE)`` (``δP`` the error of P's fit,
``Σ_P``; ``δE`` the extrinsic's, ``Σ_E`` its ``extrinsic_covariance``), the errors of P's fit
are strongly correlated over one window (the same measurements make every one of them), so they
are taken as ONE error shared by all the rider's rows in the fit, as an uncertain extrinsic is:
``T_world_P(t_i) · E · Exp(ε)`` with ``ε = Ad(E⁻¹) δP + δE``, ``Σ_ε = Ad(E⁻¹) Σ_P Ad(E⁻¹)ᵀ +
Σ_E``, ``Σ_P`` P's covariance at the reference row's time (the rider's row taken nearest the
fit's time). The joint fit of uncertain extrinsics (:mod:`dqpose.fusion.extrinsics`) then
estimates the body with ``ε`` integrated out; it takes one extrinsic per source, so P's motion
is folded into the rows: the fit's extrinsic is ``Ext = T_world_P(t_ref) · E`` and its rows the
composed ones (``Ext · z_i' · O`` with ``z_i' = Ext⁻¹ · T_world_P(t_i) · E · Z_i``), ``ε``
entering each row through ``Ad((z_i' O)⁻¹)``: exact while P moves little over the window, an
approximation of the per-row ``Ad((Z_i O)⁻¹)`` as it moves more.

A parent that is a static or a static body is the frame tree's (:func:`dqpose.frames.frame_pose`);
a tick waits for the sources of the body at the root of the parent's chain, and an answer holds
until that body changes too. Two bodies a rider sees share its ``ε``: a Lookup between them fits
them together (:meth:`Riders.joint`). Bodies without riders keep the C fast paths
(:meth:`Riders.rides`: one set look-up per body).
"""
from __future__ import annotations

import dataclasses
import threading
from typing import TYPE_CHECKING, Mapping, NamedTuple, Optional

import numpy as np

from dqpose import dq, lie
from dqpose.errors import WorldError, WorldInfeasible, known_from, seconds_text
from dqpose.frames import frame_pose
from dqpose.fusion.api import fuse_joint_rows, fuse_static_rows, fuse_world_rows
from dqpose.fusion.results import Dropped, Fused
from dqpose.limits import ANSWER_ROWS

if TYPE_CHECKING:
    from dqpose.fusion import Source
    from dqpose.world import World

_IDENT = dq.identity()


class _Composed(NamedTuple):
    """One body's rows with its riders' composed (:meth:`Riders.compose`): poses, covariances,
    sources, stamps and taken times; ``keep`` those whose parent is known (``why`` the others',
    by row), ``table`` the sources as the fit takes them (``riders`` its riders' entries) at
    ``at``."""
    Z: np.ndarray
    S: np.ndarray
    names: tuple
    times: np.ndarray
    taken: np.ndarray
    keep: np.ndarray
    why: dict
    table: dict
    riders: dict
    at: float

    def kept(self) -> np.ndarray:
        """The rows kept, or a ValueError naming why the first is not."""
        kept = np.flatnonzero(self.keep)
        if not kept.size:
            first = min(self.why)
            raise ValueError(Dropped(first, self.names[first], 0.0, 0.0,
                                     self.why[first]).reason)
        return kept


class Riders:
    """A world's riders (source -> parent, from its configuration's source ``table``) and their
    fits; without riders, what a tick waits for and an answer depends on are the body's own."""

    def __init__(self, world: "World", table: Mapping[str, "Source"]):
        self._world = world
        self.parents = {name: s.parent for name, s in table.items() if s.parent}
        self._composing = threading.local()    # the bodies whose fit a thread is composing

    def rides(self, *bodies: str) -> bool:
        """Whether a rider ever fed one of ``bodies`` ("" the world: none; the lock held)."""
        parents, w = self.parents, self._world
        return any(s in parents for b in bodies if b for s in w.fed(b))

    def parents_of(self, body: str) -> list[str]:
        """The bodies the riders that ever fed ``body`` ride on (their parents' roots in the
        frame tree: a static's body), once each (the lock held)."""
        parents, w = self.parents, self._world
        return list(dict.fromkeys(w.tree.root(parents[s]) for s in w.fed(body) if s in parents))

    @staticmethod
    def check(table: Mapping[str, "Source"], arms: Mapping[str, str], acceleration_psd) -> None:
        """A configuration's riders: an arm whose source rides on a body (an arm on a moving
        base) refused for now (FAILED_PRECONDITION); a rider beside an ``acceleration_psd``
        refused, its fit being the uncertain-extrinsic one, which that model does not have."""
        if acceleration_psd is not None and np.any(acceleration_psd):
            for k, (name, s) in enumerate(table.items()):
                if s.parent:
                    raise WorldError(None, f"sources[{k}].parent", f"source {name!r} rides on "
                                     f"{s.parent!r}: its rows carry their parent's covariance "
                                     f"as an uncertain extrinsic, not fitted with "
                                     f"options.acceleration_psd")
        for arm, src in arms.items():
            if table[src].parent:
                raise WorldInfeasible(None, f"arms[{arm!r}]", f"source {src!r} rides on "
                                      f"{table[src].parent!r}: an arm on a moving base is not "
                                      f"supported (its source's parent must be the world)")

    def waited(self, body: str) -> dict:
        """``body``'s sources' newest taken with those of the bodies its riders ride on: what a
        tick of ``body`` waits for (:func:`dqpose.world_ticks.horizon`)."""
        w = self._world
        if not self.parents:
            return w.fed(body)
        out: dict = dict(w.fed(body))
        for p in self.parents_of(body):
            if p != body and w.tracker.has(p):
                out.update(((p, s), at) for s, at in w.fed(p).items())
        return out

    def cost(self, body: str, rows: np.ndarray) -> int:
        """What a fit of ``body``'s ``rows`` costs, in rows of a plain fit: its rows, and a
        parent's fit (its tick window's rows and an answer's overhead) for each rider's row."""
        if not self.parents or not self.rides(body):
            return len(rows)
        w = self._world
        t = w.tracker
        riding = int(np.count_nonzero(t.riding[t.store.codes[rows]]))
        parent = max((len(t.rows_ending(p, t.newest(p), w.options.window))
                      for p in self.parents_of(body) if t.has(p)), default=0)
        return len(rows) + riding * (parent + ANSWER_ROWS)

    def version(self, body: str):
        """What ``body``'s answers depend on: its version (:meth:`Tracker.version`), and with
        riders its parents' too."""
        t = self._world.tracker
        own = t.version(body)
        if not self.parents or not self.rides(body):
            return own
        return (own,) + tuple(t.version(p) for p in self.parents_of(body) if p != body)

    def compose(self, rows: np.ndarray, time: Optional[float]) -> Optional[_Composed]:
        """``rows`` (one body's, the lock held) with its riders' rows composed with their
        parents' poses (the module's docstring) for a fit at ``time`` (None: the rows' newest),
        or None when no row is a rider's."""
        w = self._world
        t = w.tracker
        s = t.store
        names = t.row_sources(rows)
        riding = [k for k, n in enumerate(names) if n in self.parents]
        if not riding:
            return None
        Z, S = s.world(rows)
        taken = s.taken[rows]
        at = float(taken.max()) if time is None else float(time)
        keep = np.ones(len(rows), bool)
        why: dict[int, str] = {}
        table = dict(t.options.table)
        body = self._body_of(rows)
        riders = {}
        for src in dict.fromkeys(names[k] for k in riding):
            idx = [k for k in riding if names[k] == src]
            got = self._compose(src, body, idx, taken, Z, why)
            keep[list(why)] = False
            if got is not None:
                table[src] = riders[src] = got(at)
        return _Composed(Z, S, names, s.times[rows], taken, keep, why, table, riders, at)

    def fit(self, rows: np.ndarray, time: Optional[float], nis: bool,
            joint: bool, static: bool = False) -> Optional[tuple[Fused, np.ndarray]]:
        """The fit of ``rows`` (one body's, the lock held) composed (:meth:`compose`), or None
        when no row is a rider's; ``static``: the one-instant fit of a static body
        (``Tracker.estimate``'s ``fit="static"``). The rows left out are listed last, dropped
        with why."""
        c = self.compose(rows, time)
        if c is None:
            return None
        kept = c.kept()
        o = self._world.tracker.options._replace(table=c.table)
        used = tuple(c.names[k] for k in kept)
        f = (fuse_static_rows(c.Z[kept], c.S[kept], used, o) if static else
             fuse_world_rows(c.Z[kept], c.S[kept], used, c.times[kept], time, o, nis, joint))
        out = np.flatnonzero(~c.keep)
        at = c.at if f.time is None else f.time
        dropped = tuple(Dropped(kept.size + j, c.names[k], float(at - c.taken[k]), 0.0,
                                c.why[k]) for j, k in enumerate(out.tolist()))
        ids = self._world.tracker.store.ids[rows]
        return (dataclasses.replace(f, dropped=f.dropped + dropped),
                np.concatenate([ids[kept], ids[out]]))

    def joint(self, a: str, b: str, at: float) -> Optional[tuple]:
        """Bodies ``a`` and ``b`` (known; riders among their rows) fitted together over the
        uncertain sources they share, a rider's shared error among them (one ``ε`` a source,
        :mod:`dqpose.fusion.extrinsics`): ``(X_a, X_b, P)`` with ``P`` their joint covariance
        ``(12, 12)``; None when they share none (the lock held)."""
        w = self._world
        t = w.tracker
        table = dict(t.options.table)
        parts: list[tuple] = []
        composed: dict = {}
        for body in (a, b):
            part, riders = w.fit_of(body, w.rows_for(body, at), lambda r: self._part(r, at))
            parts.append(part)
            for name, src in riders.items():
                composed.setdefault(name, src)       # one extrinsic a source: a's
        table.update(composed)
        common = set(parts[0][2]) & set(parts[1][2])
        if not any(n in table and not table[n].exact for n in common):
            return None
        o = t.options._replace(table=table)
        starts = [fuse_world_rows(Z, S, names, times, at, o, False, False)
                  for Z, S, names, times in parts]
        (Xa, Xb), P = fuse_joint_rows(parts, starts, at, o)
        return Xa, Xb, P

    def _part(self, rows: np.ndarray, at: float) -> tuple[tuple, dict]:
        """A body's rows of a joint fit at ``at`` (those kept, composed) and its riders'
        sources as the fit takes them."""
        c = self.compose(rows, at)
        if c is None:
            t = self._world.tracker
            Z, S = t.store.world(rows)
            return (Z, S, t.row_sources(rows), t.store.times[rows]), {}
        kept = c.kept()
        return (c.Z[kept], c.S[kept], tuple(c.names[k] for k in kept), c.times[kept]), c.riders

    def _body_of(self, rows: np.ndarray) -> str:
        t = self._world.tracker
        code = int(t.store.body[rows[0]])
        return next(b for b, c in t.body_codes.items() if c == code)

    def _compose(self, src: str, body: str, idx: list, taken: np.ndarray, Z: np.ndarray,
                 why: dict):
        """Rows ``idx`` of rider ``src`` composed in place with its parent's pose at their taken
        times (those it is not known at named in ``why``); the source as the fit takes it, at
        a fit's time, or None when no row is kept."""
        w = self._world
        parent = self.parents[src]
        poses: dict[float, tuple] = {}
        good = []
        for k in idx:
            at = float(taken[k])
            if at not in poses:
                poses[at] = self._parent_pose(parent, body, at)
            got = poses[at]
            if isinstance(got, str):
                why[k] = got
                continue
            Z[k] = dq.mul(got[0], Z[k])
            good.append(k)
        if not good:
            return None
        src_ = w.tracker.options.table[src]

        def source(at: float):
            ref = min(good, key=lambda k: abs(float(taken[k]) - at))
            P, C = poses[float(taken[ref])]
            E = _IDENT if src_.extrinsic is None else src_.extrinsic
            A = lie.adjoint(dq.conj(E))
            cov = A @ C @ A.T
            if src_.extrinsic_covariance is not None:
                cov = cov + src_.extrinsic_covariance
            cov = 0.5 * (cov + cov.T)
            return dataclasses.replace(src_, extrinsic=dq.normalize(dq.mul(P, E)), parent="",
                                       extrinsic_covariance=cov if np.any(cov) else None)
        Z[good] = dq.normalize(Z[good])
        return source

    def _parent_pose(self, parent: str, body: str, at: float):
        """``T_world_parent`` at ``at`` and its covariance (a body's own fit, else the frame
        tree's, :func:`dqpose.frames.frame_pose`), or why it is not known there."""
        w = self._world
        stack = getattr(self._composing, "bodies", None)
        if stack is None:
            stack = self._composing.bodies = []
        root = w.tree.root(parent)
        if root == body or root in stack:
            return f"its parent {parent!r} rides on {body!r} (a cycle)"
        if root and not w.tracker.has(root):
            return (f"its parent {parent!r} is not known at {seconds_text(at)} (no measurement "
                    f"of {root!r})")
        stack.append(body)
        try:
            if parent == root and root not in w.tree.static_bodies:
                return w.pose_only(parent, at)     # a body: its own fit, the C path
            p = frame_pose(w, parent, at)
            return p.pose, p.covariance
        except (LookupError, ValueError):
            t = w.tracker
            return (f"its parent {parent!r} is not known at {seconds_text(at)} ("
                    f"{known_from(root, t.oldest(root), t.newest(root))})")
        finally:
            stack.pop()
