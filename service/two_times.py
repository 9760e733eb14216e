"""tf2's advanced lookup: the target frame at ``time``, the source frame at ``source_time``,
through a ``fixed`` frame held still between the two times,

    T_target(t)_source(s) = T_target_fixed(t) · T_fixed_source(s)
                          = T_w_target(t)⁻¹ · T_w_fixed(t) · T_w_fixed(s)⁻¹ · T_w_source(s),

each frame's pose its root's (:mod:`dqpose.frames`: a body's Lookup fit at its time,
:meth:`dqpose.world.World.pose`'s window; a static body's one pose; the world "", exact) composed
with its offset in the root (its chain of extrinsics and statics, the same at every time: the
fixed frame's cancels, so any frame fixed on a root holds it still). ``time`` 0 is the newest
time the bodies target and source hang from are both known at (a Lookup's rule),
``source_time`` 0 is ``time``; at one time the answer is :meth:`World.relative`'s.

The covariance model. Each factor k is an estimate with right perturbation ``δ_k``; the answer's
right perturbation is ``ξ = Σ_k G_k δ_k`` (``G_k``: the adjoint of the inverse of what follows
factor k in the product, and ``−Ad(T_k)`` first for an inverted factor), so ``Cov ξ = G Σ Gᵀ``
over the joint covariance ``Σ`` of the factors. Its diagonal blocks are the fits' covariances;
two fits of the same body at two times share the measurements both windows hold, and to first
order the Gauss-Newton estimates ``x_k = P_k Σ_f J_kfᵀ W_f e_f`` over their factors f (state:
pose, twist, and one error per source with an ``extrinsic_covariance``; ``P_k`` the inverse
information with the priors; ``J_kf`` the Jacobians of :mod:`dqpose.fusion.motion` and
:mod:`dqpose.fusion.extrinsics`, ``W_i = Σ_i⁻¹`` in the world frame) have
``Cov(x_1, x_2) = P_1 (Σ_{i∈R_1∩R_2} J_1iᵀ W_i J_2i + Σ_s Σ_E,s⁻¹) P_2``: the rows both windows
hold, and the prior of each uncertain mount both estimate (one error: it cancels in the body's
motion between the two times); its pose block is their block. Fits of different bodies are
independent, and so are the offsets of different frames; a static body's pose and a frame's
offset are one estimate at both times.

Not modelled: errors two bodies' fits at two different times share (a source's uncertain
extrinsic or estimated latency: at one time :meth:`World.relative` fits them jointly); a body
fed by riders (its rows composed with a parent's fit, :mod:`dqpose.riders`: its fits at two times
taken as independent); the latencies a fit estimates (left out of ``P_k``); a robust fit's gate
(its inliers taken as given); ``acceleration_psd``'s correlated residuals (the shared rows taken
as white noise); the links two frames' offsets share below their root (a static both hang
from).
"""
from __future__ import annotations

import math
from typing import NamedTuple, Optional

import numpy as np

from dqpose import dq, lie
from dqpose.body_pose import BodyPose, body_name
from dqpose.errors import WorldError
from dqpose.fusion.extrinsics import uncertain_extrinsics
from dqpose.fusion.motion import Model, motion_jacobian
from dqpose.fusion.results import DOF
from dqpose.fusion.validation import checked_seconds, twist_information

IDENTITY = dq.identity()


class _Fit(NamedTuple):
    """A body's Lookup fit at ``time``: its pose and covariance, and what another fit of the
    body needs for their cross-covariance: the ids of its inlier rows, their Jacobians ``J``
    ``(n, 6, d)`` and weights ``W`` ``(n, 6, 6)``, ``P`` ``(d, d)``, and ``priors``: per
    uncertain source its error's first column in the state and its prior's information."""
    body: str
    time: float
    pose: np.ndarray
    covariance: np.ndarray
    ids: np.ndarray
    J: np.ndarray
    W: np.ndarray
    P: np.ndarray
    priors: tuple = ()


def relative_at(world, target: str, time: float, source: str, source_time: float = 0.0,
                fixed: str = ""):
    """``T_target(time)_source(source_time)`` through ``fixed`` (see the module) as a
    :class:`dqpose.world.BodyPose` at ``time``: ``WorldError``, ``NotFound`` or ``OutOfRange``
    as :meth:`World.relative` names them."""
    target, source = body_name(target, "target"), body_name(source, "source")
    fixed = body_name(fixed, "fixed_frame")
    try:
        checked_seconds(time, "time")
        checked_seconds(source_time, "source_time")
    except ValueError as e:
        raise WorldError.of(e) from None
    tree = world.tree
    roots = {f: tree.root(f) for f in (target, fixed, source)}
    for root in set(roots.values()) - {""}:
        world.newest(root)          # a frame the world knows (NotFound names what it holds)
    at = float(time) if time != 0.0 else _newest_both(world, roots, target, source, fixed)
    s = at if source_time == 0.0 else float(source_time)
    if s == at:
        return world.relative(target, source, at)
    made: dict = {}
    factors = [(_offset(tree, target, made), True), (_root(world, roots[target], at, made), True),
               (_root(world, roots[fixed], at, made), False),
               (_root(world, roots[fixed], s, made), True),
               (_root(world, roots[source], s, made), False), (_offset(tree, source, made), False)]
    pose, cov = _compose([(f, inv) for f, inv in factors if f is not None])
    return BodyPose(source, at, pose, cov, None)


def _newest_both(world, roots: dict, target: str, source: str, fixed: str) -> float:
    """``time`` 0: the newest time the moving bodies target and source hang from are both
    known at (the fixed frame's when neither moves; 0 when nothing does)."""
    statics = world.tree.static_bodies
    for frames in ((target, source), (fixed,)):
        moving = {roots[f] for f in frames} - {""} - set(statics)
        if moving:
            return min(world.newest(b) for b in moving)
    return 0.0


def _root(world, root: str, at: float, made: dict) -> Optional[_Fit]:
    """The factor of a frame's root at ``at``: None for the world; a static body's one pose
    (the same factor at every time); a body's fit."""
    from dqpose import frames
    if not root:
        return None
    if root in world.tree.static_bodies:
        if root not in made:
            with world.lock.read():
                f = frames.static_fit(world, root)
            made[root] = _constant(root, f.mean, f.covariance)
        return made[root]
    if (root, at) not in made:
        made[(root, at)] = _fit(world, root, at)
    return made[(root, at)]


def _offset(tree, frame: str, made: dict) -> Optional[_Fit]:
    """The factor of ``frame`` in its root (its chain of extrinsics and statics, the same at
    every time); None for a root."""
    root = tree.root(frame)
    if frame == root:
        return None
    key = ("offset", frame)
    if key not in made:
        X, P = tree.offset(frame, root)
        made[key] = _constant(f"\0offset {frame}", X, np.zeros((DOF, DOF)) if P is None else P)
    return made[key]


def _constant(name: str, pose: np.ndarray, covariance: np.ndarray) -> _Fit:
    """A factor with no rows: nothing shared with another but itself."""
    none = np.empty(0)
    return _Fit(name, math.nan, np.asarray(pose), np.asarray(covariance), np.empty(0, np.int64),
                none, none, none)


def _fit(world, body: str, at: float) -> _Fit:
    """``body``'s Lookup fit at ``at`` with what its cross-covariance needs (see the module).
    Read under the world's read lock, from its tracker's rows: this module is the World's."""
    with world.lock.read():
        world.check_known(body)
        t = world.tracker
        rows = world.rows_for(body, at)
        f, ids = world.fit_of(body, rows,
                               lambda r: t.estimate(None, at, rows=r, nis=False, ids=True))
        Z, S = t.store.world(rows)
        names = t.row_sources(rows)
        dt = t.taken_of(rows) - f.time
        twist_cov, table = world.options.twist_covariance, t.table
        riders = world.riders.rides(body)
    keep = np.asarray(f.inliers)
    if riders:          # rows composed with a parent's fit: no shared term modelled
        return _constant(body, f.mean, f.covariance)
    # one instant without a twist prior is the static fit: the pose alone
    twist = f.twist is not None
    Wp = None if twist_cov is None or not twist else twist_information(twist_cov)[1]
    n = keep.size
    model = Model(dt[keep], np.zeros(n), -np.ones(n, dtype=np.int64), np.empty(0), np.empty(0),
                   twist, Wp)
    V = np.asarray(f.twist) if twist else np.zeros(DOF)
    r = np.asarray(f.residuals)[keep]
    ext = uncertain_extrinsics([names[i] for i in keep], table)
    k = 0 if ext is None else len(ext.names)
    # r_i moves by -G_i for the state and by Jr⁻¹(r_i) A_i for an extrinsic's error
    # (dqpose.fusion.motion, dqpose.fusion.extrinsics)
    J = np.zeros((n, DOF, model.dim + DOF * k))
    J[:, :, :model.dim] = -motion_jacobian(V, dt[keep], r, model)
    H = np.zeros((J.shape[2],) * 2)
    priors = []
    for s in range(k):
        assert ext is not None
        col, mine = model.dim + DOF * s, ext.slot == s
        A = lie.adjoint(dq.mul(dq.conj(Z[keep][mine]), ext.E[s]))
        J[mine, :, col:col + DOF] = lie.se3_right_jacobian_inv(r[mine]) @ A
        H[col:col + DOF, col:col + DOF] = ext.info[s]
        priors.append((ext.names[s], col, ext.info[s]))
    W = np.linalg.inv(S[keep])
    H += np.einsum("nia,nij,njb->ab", J, W, J)
    if Wp is not None:
        H[6:12, 6:12] += Wp
    return _Fit(body, float(f.time), np.asarray(f.mean), np.asarray(f.covariance),
                np.asarray(ids)[keep], J, W, np.linalg.inv(H), tuple(priors))


def cross_covariance(a: _Fit, b: _Fit) -> np.ndarray:
    """``Cov(δ_a, δ_b)`` ``(6, 6)`` of two fits of the same body: ``P_a (Σ J_aᵀ W J_b) P_b``
    over the rows both used and the priors of the uncertain extrinsics both estimate, its pose
    block."""
    shared, ia, ib = np.intersect1d(a.ids, b.ids, assume_unique=True, return_indices=True)
    M = np.zeros((a.P.shape[0], b.P.shape[0]))
    if shared.size:
        M += np.einsum("nia,nij,njb->ab", a.J[ia], a.W[ia], b.J[ib])
    theirs = {name: col for name, col, _ in b.priors}
    for name, col, info in a.priors:
        if name in theirs:
            M[col:col + DOF, theirs[name]:theirs[name] + DOF] += info
    if not M.any():
        return np.zeros((DOF, DOF))
    return (a.P @ M @ b.P)[:DOF, :DOF]


def _block(a: _Fit, b: _Fit, shared: bool) -> np.ndarray:
    """The joint covariance's block of two factors' fits (``shared`` False: the rows two fits
    share left out, every fit independent)."""
    if a is b:
        return a.covariance
    if a.body != b.body or not shared:
        return np.zeros((DOF, DOF))
    return cross_covariance(a, b)


def _compose(factors: list, shared: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """The product of ``factors`` (``(fit, inverted)``, in order) and its covariance ``G Σ
    Gᵀ`` (``shared`` False: as if the fits were independent, what the tests compare with)."""
    if not factors:
        return IDENTITY.copy(), np.zeros((DOF, DOF))
    poses = [dq.conj(f.pose) if inv else f.pose for f, inv in factors]
    G, after = [], IDENTITY
    for (f, inv), pose in zip(reversed(factors), reversed(poses)):
        g = lie.adjoint(dq.conj(after))
        G.append(-g @ lie.adjoint(f.pose) if inv else g)
        after = dq.mul(pose, after)
    G.reverse()
    cov = np.zeros((DOF, DOF))
    for (a, _), ga in zip(factors, G):
        for (b, _), gb in zip(factors, G):
            cov += ga @ _block(a, b, shared) @ gb.T
    return after, 0.5 * (cov + cov.T)
