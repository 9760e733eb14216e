"""The closed form (Daniilidis 1999, dual quaternions) over all pairs of samples, Huber-reweighted.

Motions between all pairs ``i < j`` (not only consecutive ones) satisfy
``A_j⁻¹A_i · X = X · C_j C_i⁻¹``; each pair's dual quaternions are put in one hemisphere
(scalar parts ≥ 0: the short screw both sides), pairs that rotate less than
``MIN_PAIR_ANGLE`` or nearly half a turn (sign ill-defined) are left out, the 6 m × 8 system
is solved by SVD and re-solved with Huber weights on each pair's residual (robust averaging).
``Z`` is then the DIB mean (:func:`dqpose.dq.dib`) of the per-sample ``A_i X C_i``.
"""
from __future__ import annotations

import numpy as np

from dqpose import dq, lie

MIN_PAIR_ANGLE = np.radians(2.0)      # pairs rotating less say little about X's rotation
MAX_PAIR_ANGLE = np.radians(170.0)    # near half a turn the hemisphere of a pair is ambiguous


def hemisphere(d: np.ndarray) -> np.ndarray:
    return np.where(d[..., :1] < 0.0, -d, d)


def motions(A, C, i, j):
    """The pair motions ``A_j⁻¹ A_i`` and ``C_j C_i⁻¹`` in one hemisphere each."""
    a = hemisphere(dq.mul(dq.inv(A[j]), A[i]))
    b = hemisphere(dq.mul(C[j], dq.inv(C[i])))
    return a, b


def rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Daniilidis' 6×8 block per pair: ``[[a−b, (a+b)^, 0, 0], [a'−b', (a'+b')^, a−b, (a+b)^]]``
    on the vector parts; ``T · [q; q'] = 0`` for the true ``X = (q, q')``."""
    m = a.shape[0]
    av, bv, ad, bd = a[:, 1:4], b[:, 1:4], a[:, 5:8], b[:, 5:8]
    T = np.zeros((m, 6, 8))
    T[:, :3, 0] = av - bv
    T[:, :3, 1:4] = lie.so3_hat(av + bv)
    T[:, 3:, 0] = ad - bd
    T[:, 3:, 1:4] = lie.so3_hat(ad + bd)
    T[:, 3:, 4] = av - bv
    T[:, 3:, 5:8] = lie.so3_hat(av + bv)
    return T


def _null_dq(T: np.ndarray) -> np.ndarray:
    """The unit dual quaternion in the two-dimensional near-null space of ``T`` (m·6, 8)."""
    _, _, Vt = np.linalg.svd(T, full_matrices=False)
    return unit_in_span(Vt[-2], Vt[-1])


def unit_in_span(v1: np.ndarray, v2: np.ndarray) -> np.ndarray:
    """The unit dual quaternions ``λ1 v1 + λ2 v2`` (``(..., 8)`` each, a basis of the near-null
    space): ``(λ1, λ2)`` with ``q·q' = 0``, a quadratic form M in ``(λ1, λ2)``, at its null
    direction with the larger ``|q|`` (the other is the pure-dual, translation-only solution);
    under noise M has none, and its eigenvector nearest to one is taken."""
    u1, d1, u2, d2 = v1[..., :4], v1[..., 4:], v2[..., :4], v2[..., 4:]
    M = np.empty(v1.shape[:-1] + (2, 2))
    M[..., 0, 0], M[..., 1, 1] = (u1 * d1).sum(-1), (u2 * d2).sum(-1)
    M[..., 0, 1] = M[..., 1, 0] = 0.5 * ((u1 * d2).sum(-1) + (u2 * d1).sum(-1))
    e, R = np.linalg.eigh(M)
    # two candidates (λ1, λ2) each: the null directions e0 y0² + e1 y1² = 0 where M has them,
    # else twice its eigenvector nearest to one
    c = np.sqrt(np.abs(e[..., ::-1]))
    cands = np.stack([R @ c[..., :, None], R @ (c * [1.0, -1.0])[..., :, None]], -3)[..., 0]
    near = np.where((np.abs(e[..., 0]) <= np.abs(e[..., 1]))[..., None], R[..., 0], R[..., 1])
    cands = np.where((e[..., 0] * e[..., 1] < 0.0)[..., None, None], cands, near[..., None, :])
    q = cands[..., :1] * u1[..., None, :] + cands[..., 1:] * u2[..., None, :]   # (..., 2, 4)
    norm = (q * q).sum(-1)
    best = (norm[..., 1] > norm[..., 0])[..., None]
    lam = np.where(best, cands[..., 1, :], cands[..., 0, :])
    lam = lam / np.sqrt(np.where(best[..., 0], norm[..., 1], norm[..., 0]))[..., None]
    x = lam[..., :1] * v1 + lam[..., 1:] * v2
    return dq.normalize(hemisphere(x))


def closed_form(A, C, use: np.ndarray, robust: bool = True):
    """Daniilidis over all usable pairs, Huber-reweighted; ``Z`` the DIB mean of ``A_i X C_i``.
    Returns ``(X, Z, number of pairs)``, or None when too few pairs rotate."""
    idx = np.flatnonzero(use)
    i, j = np.triu_indices(len(idx), 1)
    i, j = idx[i], idx[j]
    a, b = motions(A, C, i, j)
    ang = 2.0 * np.arccos(np.clip(a[:, 0], -1.0, 1.0))
    keep = (ang > MIN_PAIR_ANGLE) & (ang < MAX_PAIR_ANGLE)
    if np.count_nonzero(keep) < 2:
        return None
    a, b = a[keep], b[keep]
    T = rows(a, b)
    w = np.ones(len(a))
    X = None
    for _ in range(3 if robust else 1):
        X = _null_dq((T * np.sqrt(w)[:, None, None]).reshape(-1, 8))
        if not robust:
            break
        e = np.linalg.norm(T @ X, axis=1)
        s = 1.4826 * np.median(e) + 1e-15
        k = 2.0 * s
        w = np.where(e <= k, 1.0, k / np.maximum(e, 1e-300))
    Zi = dq.mul(dq.mul(A[use], X), C[use])
    Z = dq.dib(Zi)
    return X, Z, int(len(a))
