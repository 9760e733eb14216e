"""Corner level: maximum likelihood on the reprojection of the board's corners through
``C_i = X⁻¹ A_i⁻¹ Z``, from the pose-level answer, with an optional focal-length scale, an
optional board scale, per-view corner noise, and a correction of each robot pose under the
robot's noise (given or estimated)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple, Optional

import numpy as np

from dqpose import dq, lie
from dqpose.errors import FieldError, Infeasible
from dqpose.handeye.likelihood import TOL
from dqpose.handeye.setups import EYE_IN_HAND, reading

_MIN_CORNERS = 4


@dataclass
class _Views:
    points: np.ndarray      # (N, 3) board points, all views stacked
    pixels: np.ndarray      # (N, 2) their detections
    view: np.ndarray        # (N,) the sample each belongs to
    K: np.ndarray           # (n, 3, 3)

    def subset(self, idx) -> "_Views":
        """The views of the samples ``idx`` (sorted), renumbered ``0 … len(idx) − 1``."""
        sel = np.isin(self.view, idx)
        return _Views(self.points[sel], self.pixels[sel], np.searchsorted(idx, self.view[sel]),
                      self.K[idx])


def corner_views(corners, n: int) -> _Views:
    """``corners``: one ``(board_points (k,3), image_points (k,2), K (3,3))`` per sample (a
    mapping with those keys also does); undistorted pixels."""
    try:
        items = list(corners)
    except TypeError:
        raise FieldError(f"corners: expected one entry per sample, got "
                         f"{type(corners).__name__}") from None
    if len(items) != n:
        raise FieldError(f"corners: {len(items)} views for {n} samples (one per sample)")
    P, U, V, K = [], [], [], []
    for i, item in enumerate(items):
        if isinstance(item, dict):
            item = (item.get("board_points"), item.get("image_points"), item.get("K"))
        try:
            b, u, k = item
        except (TypeError, ValueError):
            raise FieldError(f"corners[{i}]: expected (board_points, image_points, K)") from None
        arrays = []
        for name, x, shape in (("board_points", b, (None, 3)), ("image_points", u, (None, 2)),
                               ("K", k, (3, 3))):
            try:
                a = np.asarray(x, dtype=np.float64)
            except (TypeError, ValueError):
                raise FieldError(f"corners[{i}].{name}: expected numbers") from None
            if a.ndim != 2 or any(w is not None and d != w for d, w in zip(a.shape, shape)):
                want = ", ".join("k" if w is None else str(w) for w in shape)
                raise FieldError(f"corners[{i}].{name}: expected shape ({want}), got {a.shape}")
            if not np.all(np.isfinite(a)):
                raise FieldError(f"corners[{i}].{name}: contains NaN or infinity")
            arrays.append(a)
        b, u, k = arrays
        if len(b) != len(u):
            raise FieldError(f"corners[{i}].image_points: {len(u)} points for {len(b)} board "
                             f"points")
        if len(b) < _MIN_CORNERS:
            raise FieldError(f"corners[{i}].board_points: {len(b)} corners; at least "
                             f"{_MIN_CORNERS} are needed")
        if not (k[0, 0] > 0 and k[1, 1] > 0 and np.allclose(k[2], [0, 0, 1])
                and k[1, 0] == 0 and abs(k[0, 1]) < 1e-9 * k[0, 0]):
            raise FieldError(f"corners[{i}].K: not a camera matrix [[fx, 0, cx], [0, fy, cy], "
                             f"[0, 0, 1]] with fx, fy > 0")
        P.append(b)
        U.append(u)
        V.append(np.full(len(b), i))
        K.append(k)
    return _Views(np.concatenate(P), np.concatenate(U), np.concatenate(V), np.stack(K))


def _corner_cameras(F, setup, X, Z, delta):
    """``C_i = X⁻¹ A_i⁻¹ Z`` as 4×4 matrices, ``A_i`` the reading of ``F_i Exp(δ_i)``."""
    Fi = F if delta is None else dq.mul(F, lie.se3_exp(delta))
    return dq.to_matrix(dq.mul(dq.mul(dq.inv(X), dq.inv(reading(Fi, setup))), Z))


def _project(M, views: _Views, scale: float):
    """Camera points, pixels, the projection's Jacobian and the pixels' derivative by the focal
    scale."""
    R, t = M[:, :3, :3], M[:, :3, 3]
    v = views.view
    pc = (R[v] @ views.points[..., None])[..., 0] + t[v]
    K = views.K[v]
    fx, fy = K[:, 0, 0] * scale, K[:, 1, 1] * scale
    x, y, z = pc[:, 0], pc[:, 1], pc[:, 2]
    u = np.column_stack([fx * x / z + K[:, 0, 2], fy * y / z + K[:, 1, 2]])
    Jp = np.zeros((len(pc), 2, 3))
    Jp[:, 0, 0], Jp[:, 0, 2] = fx / z, -fx * x / z ** 2
    Jp[:, 1, 1], Jp[:, 1, 2] = fy / z, -fy * y / z ** 2
    ds = np.column_stack([K[:, 0, 0] * x / z, K[:, 1, 1] * y / z])   # d u / d scale
    return pc, u, Jp, ds


@dataclass
class _CornerFit:
    X: np.ndarray
    Z: np.ndarray
    P: np.ndarray            # (12, 12) marginal covariance of (X, Z)
    reprojection: np.ndarray  # (n,) RMS pixels per view, all views
    focal_scale: float
    pixel_sigma: float
    focal_sigma: float
    robot_covariance: Optional[np.ndarray]   # (6, 6) estimated robot noise, when estimated
    board_scale: float = 1.0                 # the board points' refined scale (refine_board)
    board_sigma: float = 0.0


_ROBOT_START = np.array([np.radians(0.02)] * 3 + [1e-4] * 3) ** 2   # (rad², m²) the start
_ROBOT_FLOOR = np.array([np.radians(1e-5)] * 3 + [1e-8] * 3) ** 2
_EM_ROUNDS = 12


class _Arrow(NamedTuple):
    """The corner fit's normal equations solved by their arrow structure: ``Pgg`` the global
    parameters' covariance, ``Pdd`` each view's correction's ``(n, 6, 6)``; ``cost`` the
    squared residual at the linearisation; ``moved(step)`` is ``stepᵀ H step``."""
    Pgg: np.ndarray
    Pdd: Optional[np.ndarray]
    cost: float
    moved: object


def _arrow_step(Jg, Jd, r, prior, delta, starts):
    """The Gauss–Newton step of the corner fit, ``-H⁻¹ Jᵀ r``, and the leverage ``J_k H⁻¹ J_kᵀ``
    of each pixel row, in O(views): the rows of view i depend on the global parameters (columns
    ``Jg``) and on view i's robot correction alone (``Jd``, with the prior rows ``prior[i]`` on
    it), so ``H`` is an arrow: a small global block, one 6 × 6 block per view, and their
    coupling, eliminated view by view (Schur complement). ``Jd`` None: no corrections.
    Returns ``(step, _Arrow, leverage)``."""
    Hgg = Jg.T @ Jg
    gg = Jg.T @ r
    cost = float(r @ r)
    if Jd is None:
        try:
            Pgg = np.linalg.inv(Hgg)
        except np.linalg.LinAlgError:
            raise Infeasible("corners: the corners do not determine X and Z (singular "
                             "information)") from None
        step = -Pgg @ gg
        lev = np.einsum("ki,ij,kj->k", Jg, Pgg, Jg)
        return step, _Arrow(Pgg, None, cost, lambda s: float(s @ Hgg @ s)), lev
    m = Jg.shape[1]

    def per_view(a):       # sums over each view's pixel rows (two a corner, views in order)
        return np.add.reduceat(a, 2 * starts, axis=0)

    pd = np.einsum("nij,nj->ni", prior, delta)
    Hgd = per_view(Jg[:, :, None] * Jd[:, None, :])                      # (n, m, 6)
    D = per_view(Jd[:, :, None] * Jd[:, None, :]) + np.swapaxes(prior, 1, 2) @ prior
    gd = per_view(Jd * r[:, None]) + np.einsum("nji,nj->ni", prior, pd)
    cost += float((pd ** 2).sum())
    try:
        Di = np.linalg.inv(D)
        HDi = Hgd @ Di                                                   # (n, m, 6)
        S = Hgg - np.einsum("nij,nkj->ik", HDi, Hgd)
        Pgg = np.linalg.inv(0.5 * (S + S.T))
    except np.linalg.LinAlgError:
        raise Infeasible("corners: the corners do not determine X and Z (singular "
                         "information)") from None
    step_g = -Pgg @ (gg - np.einsum("nij,nj->i", HDi, gd))
    step_d = -np.einsum("nij,nj->ni", Di, gd + np.einsum("nji,j->ni", Hgd, step_g))
    # P_gi = -Pgg HDi_i; P_ii = Di + HDi_iᵀ Pgg HDi_i
    Pgd = -np.einsum("ij,njk->nik", Pgg, HDi)                            # (n, m, 6)
    Pdd = Di + np.einsum("nji,jk,nkl->nil", HDi, Pgg, HDi)
    view = np.repeat(np.arange(len(starts)), np.diff(np.r_[starts, len(Jg) // 2]) * 2)
    lev = (np.einsum("ki,ij,kj->k", Jg, Pgg, Jg)
           + 2.0 * np.einsum("ki,kij,kj->k", Jg, Pgd[view], Jd)
           + np.einsum("ki,kij,kj->k", Jd, Pdd[view], Jd))

    def moved(s):
        sg, sd = s[:m], s[m:].reshape(-1, 6)
        return float(sg @ Hgg @ sg + 2.0 * np.einsum("i,nij,nj->", sg, Hgd, sd)
                     + np.einsum("ni,nij,nj->", sd, D, sd))

    return np.concatenate([step_g, step_d.ravel()]), _Arrow(Pgg, Pdd, cost, moved), lev


def corner_fit(F, setup, X, Z, views: _Views, inlier, robot, refine_focal: bool,
                pixel_sigma: Optional[float], refine_board: bool = False) -> _CornerFit:
    """Maximum likelihood on the corners: pixels with isotropic noise σ (given, or estimated
    per view from its reprojection errors, the fit's leverage in that view taken out: a view's
    blur, distance and obliquity set it), unknowns ``X``, ``Z`` (right perturbations), a
    focal-length scale when ``refine_focal``, and a correction ``δ_i`` of each
    robot pose ``F_i Exp(δ_i)`` under the robot noise ``robot``: given ((n, 6, 6)), estimated
    (``"estimate"``: isotropic rotation and translation variances, MacKay's evidence fixed
    point on the corrections, :func:`_mackay`), or None (robot poses exact). Gauss–Newton from
    the pose-level answer. ``refine_board`` frees a scale of the board's points too (after the
    pose level found the camera's translations at another scale: its uncertainty then enters
    the covariance)."""
    idx = np.flatnonzero(inlier)
    n_in = len(idx)
    sub = views.subset(idx)
    Fu = F[idx]
    # δ of F moves A by δ (eye_in_hand) or −Ad(F) δ (eye_to_hand: A = F⁻¹).
    toA = None if setup == EYE_IN_HAND else -lie.adjoint(Fu)
    estimate = isinstance(robot, str)
    use_robot = robot is not None
    nf = 1 if refine_focal else 0
    nb = 1 if refine_board else 0
    N = len(sub.points)
    theta = _ROBOT_START.copy()
    delta = np.zeros((n_in, 6)) if use_robot else None
    scale = board = 1.0
    corners_in = np.bincount(sub.view, minlength=n_in)
    # Corner noise per view: a view's blur, distance and obliquity set it (0.02–0.1 px among
    # clean renders of one scene), and one σ for all would weigh the noisy views as much as the
    # sharp ones and claim their errors average like the others'.
    sigma = np.full(n_in, pixel_sigma or 1.0)
    leverage = (12.0 + nf + nb) / n_in * np.ones(n_in)  # each view's share of the fitted dof
    starts = np.flatnonzero(np.r_[True, sub.view[1:] != sub.view[:-1]])   # views in order
    H = None
    settled = not estimate
    for em in range(_EM_ROUNDS + 1 if estimate else 1):
        settled = settled or em == _EM_ROUNDS
        prior = _prior_rows(robot, theta, idx) if use_robot else None
        cost = np.inf
        # While the robot's variances are still moving a couple of steps per round do; the
        # round after they settle converges.
        for _ in range(50 if settled else 2):
            M = _corner_cameras(Fu, setup, X, Z, delta)
            pts = sub.points * board
            pc, u, Jp, ds = _project(M, _Views(pts, sub.pixels, sub.view, sub.K), scale)
            _in_front(pc, sub.view, idx)
            e = (u - sub.pixels).reshape(-1)
            if pixel_sigma is None:
                sigma = _view_sigma(e, sub.view, corners_in, leverage)
            r, Jg, Jd = _whitened(e, M, sub.view, pts, pc, Jp, ds, sigma, X, toA, nf, nb,
                                  use_robot)
            step, H, lev = _arrow_step(Jg, Jd, r, prior, delta, starts)
            X, Z, scale, board, delta = _stepped(step, X, Z, scale, board, delta, nf, nb)
            # the pixel dof the fit takes, per view (REML: each σ from what the fit leaves)
            leverage = np.add.reduceat(lev.reshape(N, 2).sum(axis=1), starts)
            new = H.cost
            if H.moved(step) < TOL and abs(cost - new) <= 1e-9 * new:
                break
            cost = new
        assert H is not None                # the step loop runs at least once
        if settled:
            break
        theta, settled = _mackay(delta, H.Pdd, theta)
    assert H is not None
    P = H.Pgg
    full = None
    if use_robot:
        full = np.zeros((len(F), 6))
        full[idx] = delta
    rms = _reprojection(F, setup, X, Z, views, full, board, scale)
    P12 = 0.5 * (P[:12, :12] + P[:12, :12].T)
    dof = np.maximum(2 * corners_in - leverage, 1.0)
    pooled = float(pixel_sigma or np.sqrt(np.sum(sigma ** 2 * dof) / np.sum(dof)))
    return _CornerFit(X, Z, P12, rms, scale, pooled, float(np.sqrt(P[12, 12])) if nf else 0.0,
                      np.diag(theta) if estimate else None, board,
                      float(np.sqrt(P[12 + nf, 12 + nf])) if nb else 0.0)


def _stepped(step, X, Z, scale, board, delta, nf: int, nb: int):
    """The unknowns moved by one Gauss-Newton ``step`` (its layout: ``X``, ``Z``, the focal
    scale when ``nf``, the board's scale when ``nb``, then each view's robot correction)."""
    X = dq.mul(X, lie.se3_exp(step[:6]))
    Z = dq.mul(Z, lie.se3_exp(step[6:12]))
    if nf:
        scale *= 1.0 + step[12]
    if nb:
        board *= 1.0 + step[12 + nf]
    if delta is not None:
        delta = delta + step[12 + nf + nb:].reshape(len(delta), 6)
    return X, Z, scale, board, delta


def _view_sigma(e, view, corners_in, leverage) -> np.ndarray:
    """Each view's corner noise σ (px) from its reprojection errors ``e`` (two per corner),
    the fit's leverage in that view taken out (REML)."""
    e2 = np.bincount(view, (e.reshape(-1, 2) ** 2).sum(axis=1), minlength=len(corners_in))
    dof = np.maximum(2 * corners_in - leverage, 1.0)
    return np.sqrt(np.maximum(e2 / dof, 1e-18))


def _prior_rows(robot, theta, idx) -> np.ndarray:
    """``Σ^-1/2`` of each view's robot correction: the given robot covariances ``robot[idx]``,
    or the estimated variances ``theta`` (``robot == "estimate"``)."""
    S = (np.broadcast_to(np.diag(theta), (len(idx), 6, 6)) if isinstance(robot, str) else
         np.asarray(robot)[idx])
    e, Q = np.linalg.eigh(S)
    e = np.maximum(e, 1e-12 * e.max(axis=1, keepdims=True) + 1e-30)
    return np.swapaxes(Q / np.sqrt(e)[:, None, :], 1, 2)


def _in_front(pc, view, idx) -> None:
    """``Infeasible`` naming the first sample whose board lies behind its camera (points
    ``pc`` in the camera of ``view``, the sample ``idx[view]``)."""
    behind = pc[:, 2] <= 0.0
    if np.any(behind):
        k = int(idx[view[np.flatnonzero(behind)[0]]])
        raise Infeasible(f"corners[{k}]: the board lies behind the camera in the "
                         f"solution; do the corners belong to the poses (same order, "
                         f"same board frame)?")


def _whitened(e, M, view, pts, pc, Jp, ds, sigma, X, toA, nf: int, nb: int, use_robot: bool):
    """The pixel rows whitened by their view's σ: residuals ``e / σ``, the global columns (X, Z,
    the focal and board scales) and, with ``use_robot``, the view's robot correction's."""
    N = len(pts)
    s_row = np.repeat(sigma[view], 2)
    R = M[view, :3, :3]
    dX = np.zeros((N, 3, 6))
    dX[:, :, :3] = lie.so3_hat(pc)
    dX[:, :, 3:] = -np.eye(3)
    dZ = np.concatenate([-R @ lie.so3_hat(pts), R], axis=2)
    Jg = np.empty((2 * N, 12 + nf + nb))
    Jg[:, :6] = (Jp @ dX).reshape(2 * N, 6) / s_row[:, None]
    Jg[:, 6:12] = (Jp @ dZ).reshape(2 * N, 6) / s_row[:, None]
    if nf:
        Jg[:, 12] = ds.reshape(-1) / s_row
    if nb:       # the board's points scaled by (1 + ε): the camera's points by R p ε
        Jg[:, 12 + nf] = (Jp @ (R @ pts[..., None]))[..., 0].reshape(-1) / s_row
    Jd = None
    if use_robot:
        # A ← A Exp(δ_A) moves C by Exp(−Ad(X⁻¹) δ_A) on the left: the X column's derivative
        # times Ad(X⁻¹).
        dA = dX @ lie.adjoint(dq.inv(X))
        if toA is not None:
            dA = dA @ toA[view]
        Jd = ((Jp @ dA) / sigma[view, None, None]).reshape(2 * N, 6)
    return e / s_row, Jg, Jd


def _mackay(delta, Pdd, theta) -> tuple[np.ndarray, bool]:
    """The robot's variances re-estimated from the corrections ``delta`` (covariances ``Pdd``),
    and whether they settled. MacKay's fixed point (the evidence's stationary point):
    ``θ = Σ δ̂² / γ`` with ``γ = Σ (1 − P_kk / θ)`` the number of correction components the
    corners determine; unlike EM it drops to ~0 in a step when the robot is exact."""
    d2 = (delta ** 2).sum(axis=0)
    gam = (1.0 - np.diagonal(Pdd, axis1=1, axis2=2) / theta).sum(axis=0)
    gam = np.repeat([gam[:3].sum(), gam[3:].sum()], 3)
    num = np.repeat([d2[:3].sum(), d2[3:].sum()], 3)
    new_theta = np.maximum(num / np.maximum(gam, 1e-3), _ROBOT_FLOOR)
    return new_theta, bool(np.all(np.abs(new_theta - theta) <= 0.1 * theta + _ROBOT_FLOOR))


def _reprojection(F, setup, X, Z, views: _Views, delta, board: float, scale: float) -> np.ndarray:
    """The RMS reprojection error (px) of every view, inliers or not, at the fit."""
    M = _corner_cameras(F, setup, X, Z, delta)
    _, u, _, _ = _project(M, _Views(views.points * board, views.pixels, views.view, views.K),
                          scale)
    err = np.sum((u - views.pixels) ** 2, axis=1)
    count = np.bincount(views.view, minlength=len(F))
    return np.sqrt(np.bincount(views.view, err, minlength=len(F)) / np.maximum(count, 1))
