"""Each sample against the pose-level fit: its NIS gated at probability ``_GATE`` (the
thresholds of :mod:`~dqpose.handeye.gate`: χ²₆ with the noise given, the studentised laws with it
estimated), the reason an outlier is one, and how far X moves when a sample is left out.

The inliers' NIS is their standardised residual ``r_iᵀ (Σ_r,i − J_i P J_iᵀ)⁻¹ r_i`` (the
leave-one-out NIS to first order), the others' against the prediction ``Σ_r,i + J_i P J_iᵀ``;
the gate starts from the consensus of minimal sets (:mod:`~dqpose.handeye.consensus`), with the
noise estimated screened once more by a robust estimate of the noise (:func:`_screened`), and
re-fits until the set settles. Robust solves leave the outliers out; otherwise they stay in,
named in a warning.

False alarms on healthy data (tests/bench/bench_handeye_false_alarms.py, 8,000 genuine samples
a row): the 95 % interval of the rate of genuine samples rejected contains the nominal
``1 − _GATE`` = 0.1 % in both modes and at both noise levels (docs/benchmarks/handeye.md).
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from dqpose import dq, lie
from dqpose.errors import Infeasible
from dqpose.fusion.chi2 import chi2_quantile, gamma_p
from dqpose.handeye.checks import MIN_POSES, samples
from dqpose.handeye.consensus import consensus
from dqpose.handeye.gate import GATE_3, GATE_6, thresholds
from dqpose.handeye.likelihood import Fit, gauss_newton, linearise, standardised
from dqpose.handeye.noise import Noise
from dqpose.handeye.result import Rejection

if TYPE_CHECKING:
    from dqpose.handeye.checks import Prepared

# The robust screen's share of the samples: the noise is estimated on this fraction of them with
# the smallest NIS (the rest may be outliers), its truncation undone (:func:`_screened`).
_SCREEN_SHARE = 0.6
_SCREEN_GATE = 27.856341236012888       # χ²₆ quantile at 1 − 1e-4 (fusion.chi2_quantile)


def gated(p: Prepared, noise: Noise, robust: bool, warnings: list):
    """The fit from the consensus of minimal sets (from the closed form on the samples that pass
    screw congruence when there are too few for one), re-fitted on those the gate passes until
    the set settles: ``(fit, inliers, rejected)``. The gate runs in
    both modes; without ``robust`` its outliers are named, not left out."""
    start = consensus(p, noise, GATE_6)
    if start is None:
        inlier, X, Z = p.use & ~p.suspect, p.closed[0], p.closed[1]
    else:
        inlier, X, Z = start
    fit = gauss_newton(p.A, p.C, X, Z, noise, inlier)
    if noise.estimate:
        fit, inlier = _screened(p, noise, fit, inlier)
    for _ in range(5):
        r_all, S_all, nis_all = against(p, fit, noise, inlier)
        limit = _limits(noise, inlier)
        new = p.use & (nis_all <= limit)
        if np.count_nonzero(new) < MIN_POSES:
            # Too few would pass to solve on: the answer stands on samples the gate doubts, so
            # it says which (never silently; a given noise far too small does this too).
            doubt = np.flatnonzero(p.use & ~new)
            worst = doubt[np.argmax(nis_all[doubt] / limit[doubt])]
            warnings.append(f"{samples(doubt)}: fail the χ² gate (NIS up to "
                            f"{float(nis_all[worst]):.3g} > {float(limit[worst]):.3g}), leaving "
                            f"fewer than {MIN_POSES} samples; kept, so the answer is doubtful: "
                            f"outliers, or a given noise too small?")
            break
        if np.array_equal(new, inlier):
            break
        inlier = new
        fit = gauss_newton(p.A, p.C, fit.X, fit.Z, noise, inlier)
    r_all, S_all, nis_all = against(p, fit, noise, inlier)
    limit = _limits(noise, inlier)
    outliers = [Rejection(int(k), _reason(k, fit, p, r_all[k], S_all[k], nis_all[k], limit[k]))
                for k in np.flatnonzero(p.use & ~inlier)]
    rejected: list[Rejection] = []
    if outliers:
        what = ("rejected as outliers" if robust else
                "outliers (kept: robust mode is off)")
        warnings.append(f"{samples([r.index for r in outliers])}: {what} (" +
                        "; ".join(f"{r.index}: {r.reason}" for r in outliers) + ")")
    if robust:
        rejected = outliers
    elif not np.array_equal(inlier, p.use):
        inlier = p.use.copy()
        fit = gauss_newton(p.A, p.C, fit.X, fit.Z, noise, inlier)
    return fit, inlier, tuple(rejected)


def _limits(noise: Noise, inlier) -> np.ndarray:
    """Each sample's NIS threshold (:func:`~dqpose.handeye.gate.thresholds`): the fit's for the
    inliers, the prediction's for the others."""
    inside, outside = thresholds(noise.estimate, 6 * int(np.count_nonzero(inlier)) - 12)
    return np.where(inlier, inside, outside)


def _screened(p: Prepared, noise: Noise, fit: Fit, inlier):
    """The fit and its samples after a screen by a robust scale of the estimated noise: each
    sample's standardised residual split into its rotation and its translation (χ²₃ each), each
    block's scale from the ``_SCREEN_SHARE`` of the samples smallest in it, scaled up by what
    the truncation takes away (a χ²₃ cut at its quantile ``c`` of that share keeps
    ``P(χ²₅ ≤ c) / P(χ²₃ ≤ c)`` of its mean: the consistency factor of a minimum covariance
    determinant); the samples whose NIS at those scales fail the gate are left out, to be
    re-admitted by the gate on the noise estimated without them.

    An outlier in the start inflates the noise estimated with it, and so hides itself: 1° marker
    flips among 12 samples at 0.1° / 0.5 mm took the estimated rotation noise to 0.2–0.26°, and 7
    of 160 flips were kept. The start is the consensus of minimal sets, loose by design (the
    noise is not known there), and lets such small ones in. Only the two blocks' scales are
    robust, not the three components re-estimated on the share: on 10 samples that share
    collapsed a component (10 poses of OpenCV's geometry at 0.5° / 2 mm, seed 1032: numpy's
    LinAlgError, or two genuine samples left out and X 6 mm off at NEES 2658)."""
    idx = np.flatnonzero(inlier)
    m = len(idx)
    h = int(np.ceil(_SCREEN_SHARE * m))
    if h < 3:
        return fit, inlier
    n = p.F.shape[0]
    _, r, J, S = linearise(p.A, p.C, lie.adjoint(dq.inv(p.C)), fit.X, fit.Z, noise,
                            np.ones(n, bool))
    V = (S - J @ fit.P @ np.swapaxes(J, 1, 2))[idx]
    c = chi2_quantile(h / (m + 1), 3)
    kept = gamma_p(2.5, 0.5 * c) / gamma_p(1.5, 0.5 * c)
    nis = np.zeros(m)
    for b in (slice(0, 3), slice(3, 6)):
        Vb = 0.5 * (V[:, b, b] + np.swapaxes(V[:, b, b], 1, 2))
        rb = r[idx][:, b]
        q = np.einsum("ni,nij,nj->n", rb, np.linalg.pinv(Vb, rcond=1e-10, hermitian=True), rb)
        scale = float(np.mean(np.sort(q)[:h])) / (3.0 * kept)
        if not scale > 0.0:
            return fit, inlier
        nis += q / scale
    # The screen only leaves out, and only what is far off at the robust scales (χ²₆ at
    # 1 − 1e-4): at the gate's own threshold it left out genuine views of a camera noisier in
    # depth than the isotropic model says (KinHEC's nine station settings: 1.06 % of genuine
    # samples rejected, 0.78 % at this one, 0.52 % without a screen). The gate re-admits on the
    # noise estimated without them.
    screen = inlier.copy()
    screen[idx] = nis <= _SCREEN_GATE
    if np.array_equal(screen, inlier) or np.count_nonzero(screen) < MIN_POSES:
        return fit, inlier
    state = noise.theta, noise.step
    try:
        with np.errstate(over="raise", divide="raise", invalid="raise"):
            return gauss_newton(p.A, p.C, fit.X, fit.Z, noise, screen), screen
    except (Infeasible, np.linalg.LinAlgError, FloatingPointError):
        noise.theta, noise.step = state
        return fit, inlier


def leave_one_out(fit: Fit, idx, n: int) -> np.ndarray:
    """``(n, 2)``: how far X turns (rad) and moves (m) when each inlier ``idx`` is left out: by
    ``H⁻¹ J_iᵀ S_i⁻¹ r_i`` (Sherman–Morrison, first order); zero for the others."""
    _, y = standardised(fit)
    loo = np.zeros((n, 2))
    shift = np.einsum("ij,nkj,nk->ni", fit.P, fit.J, y)
    m = lie.se3_exp(shift[:, :6])
    loo[idx, 0] = 2.0 * np.arctan2(np.linalg.norm(m[:, 1:4], axis=1), np.abs(m[:, 0]))
    loo[idx, 1] = np.linalg.norm(dq.to_pose(m)[1], axis=1)
    return loo


def against(p: Prepared, fit: Fit, noise: Noise, inlier):
    """Residuals, their covariances and NIS of every sample against a fit: the inliers'
    standardised (leave-one-out to first order, ``Σ_r − J P Jᵀ``), the others' against the
    prediction (``Σ_r + J P Jᵀ``)."""
    n = p.F.shape[0]
    everyone = np.ones(n, bool)
    E, r, J, S = linearise(p.A, p.C, lie.adjoint(dq.inv(p.C)), fit.X, fit.Z, noise, everyone)
    sign = np.where(inlier, -1.0, 1.0)
    V = S + sign[:, None, None] * (J @ fit.P @ np.swapaxes(J, 1, 2))
    V = 0.5 * (V + np.swapaxes(V, 1, 2))
    y = np.einsum("nij,nj->ni", np.linalg.pinv(V, rcond=1e-10, hermitian=True), r)
    return r, np.array(S), np.einsum("ni,ni->n", r, y)


def _reason(k, fit: Fit, p: Prepared, r, S, nis, limit) -> str:
    if not p.use[k]:
        return "duplicate"
    # The rotation off while the board's position (the translation of the residual) is not:
    # the planar-target pose ambiguity.
    E = dq.mul(dq.mul(dq.mul(dq.inv(fit.Z), p.A[k]), fit.X), p.C[k])
    t = dq.to_pose(E)[1]
    St = S[3:, 3:]
    pos_nis = float(t @ np.linalg.solve(St, t))
    ang = float(np.linalg.norm(r[:3]))
    if ang > np.radians(3.0) and pos_nis <= GATE_3:
        return (f"marker flip? rotation off by {np.degrees(ang):.1f}° while the board's "
                f"position agrees to {1e3 * np.linalg.norm(t):.2f} mm")
    return (f"NIS {nis:.3g} > {limit:.3g}: off by {np.degrees(ang):.2f}° / "
            f"{1e3 * np.linalg.norm(t):.2f} mm")
