"""Each sample against the pose-level fit: its NIS (χ² with 6 dof) gated at probability
``_GATE``, the reason an outlier is one, and how far X moves when a sample is left out.

The inliers' NIS is their standardised residual ``r_iᵀ (Σ_r,i − J_i P J_iᵀ)⁻¹ r_i`` (the
leave-one-out NIS to first order), the others' against the prediction ``Σ_r,i + J_i P J_iᵀ``;
the gate starts from a fit on the samples that pass the screw-congruence test and re-fits until
the set settles. Robust solves leave the outliers out; otherwise they stay in, named in a warning.

False alarms on healthy data (tests/bench/bench_handeye_false_alarms.py, 4000 genuine samples a
row): 0.05–0.1 % of genuine samples rejected with the noise estimated, 0.2–0.28 % with it given
(nominal ``1 − _GATE`` = 0.1 %).
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from dqpose import dq, lie
from dqpose.handeye.checks import _MIN_POSES, _samples
from dqpose.handeye.consensus import _consensus
from dqpose.handeye.likelihood import _Fit, _fit, _linearise, _standardised
from dqpose.handeye.noise import _Noise
from dqpose.handeye.result import Rejection

if TYPE_CHECKING:
    from dqpose.handeye.checks import _Prepared

_GATE = 0.999                          # χ² probability of the robust gate
_GATE_6 = 22.457744484825192           # χ²₆ quantile at _GATE (fusion.chi2_quantile(0.999, 6))
_GATE_3 = 16.266236196238010           # χ²₃ quantile at _GATE


def _gated(p: _Prepared, noise: _Noise, robust: bool, warnings: list):
    """The fit from the consensus of minimal sets (from the closed form on the samples that pass
    screw congruence when there are too few for one), re-fitted on those the gate passes until
    the set settles: ``(fit, inliers, rejected)``. The gate runs in
    both modes; without ``robust`` its outliers are named, not left out."""
    start = _consensus(p, noise, _GATE_6)
    if start is None:
        inlier, X, Z = p.use & ~p.suspect, p.closed[0], p.closed[1]
    else:
        inlier, X, Z = start
    fit = _fit(p.A, p.C, X, Z, noise, inlier)
    for _ in range(5):
        r_all, S_all, nis_all = _against(p, fit, noise, inlier)
        new = p.use & (nis_all <= _GATE_6)
        if np.count_nonzero(new) < _MIN_POSES:
            # Too few would pass to solve on: the answer stands on samples the gate doubts, so
            # it says which (never silently; a given noise far too small does this too).
            doubt = np.flatnonzero(p.use & ~new)
            warnings.append(f"{_samples(doubt)}: fail the χ² gate (NIS up to "
                            f"{float(np.max(nis_all[doubt])):.3g} > {_GATE_6:.3g}), leaving "
                            f"fewer than {_MIN_POSES} samples; kept, so the answer is doubtful: "
                            f"outliers, or a given noise too small?")
            break
        if np.array_equal(new, inlier):
            break
        inlier = new
        fit = _fit(p.A, p.C, fit.X, fit.Z, noise, inlier)
    r_all, S_all, nis_all = _against(p, fit, noise, inlier)
    outliers = [Rejection(int(k), _reason(k, fit, p, r_all[k], S_all[k], nis_all[k]))
                for k in np.flatnonzero(p.use & ~inlier)]
    rejected: list[Rejection] = []
    if outliers:
        what = ("rejected as outliers" if robust else
                "outliers (kept: robust mode is off)")
        warnings.append(f"{_samples([r.index for r in outliers])}: {what} (" +
                        "; ".join(f"{r.index}: {r.reason}" for r in outliers) + ")")
    if robust:
        rejected = outliers
    elif not np.array_equal(inlier, p.use):
        inlier = p.use.copy()
        fit = _fit(p.A, p.C, fit.X, fit.Z, noise, inlier)
    return fit, inlier, tuple(rejected)


def _leave_one_out(fit: _Fit, idx, n: int) -> np.ndarray:
    """``(n, 2)``: how far X turns (rad) and moves (m) when each inlier ``idx`` is left out: by
    ``H⁻¹ J_iᵀ S_i⁻¹ r_i`` (Sherman–Morrison, first order); zero for the others."""
    _, y = _standardised(fit)
    loo = np.zeros((n, 2))
    shift = np.einsum("ij,nkj,nk->ni", fit.P, fit.J, y)
    m = lie.se3_exp(shift[:, :6])
    loo[idx, 0] = 2.0 * np.arctan2(np.linalg.norm(m[:, 1:4], axis=1), np.abs(m[:, 0]))
    loo[idx, 1] = np.linalg.norm(dq.to_pose(m)[1], axis=1)
    return loo


def _against(p: _Prepared, fit: _Fit, noise: _Noise, inlier):
    """Residuals, their covariances and NIS of every sample against a fit: the inliers'
    standardised (leave-one-out to first order, ``Σ_r − J P Jᵀ``), the others' against the
    prediction (``Σ_r + J P Jᵀ``)."""
    n = p.F.shape[0]
    everyone = np.ones(n, bool)
    E, r, J, S = _linearise(p.A, p.C, lie.adjoint(dq.inv(p.C)), fit.X, fit.Z, noise, everyone)
    sign = np.where(inlier, -1.0, 1.0)
    V = S + sign[:, None, None] * (J @ fit.P @ np.swapaxes(J, 1, 2))
    V = 0.5 * (V + np.swapaxes(V, 1, 2))
    y = np.einsum("nij,nj->ni", np.linalg.pinv(V, rcond=1e-10, hermitian=True), r)
    return r, np.array(S), np.einsum("ni,ni->n", r, y)


def _reason(k, fit: _Fit, p: _Prepared, r, S, nis) -> str:
    if not p.use[k]:
        return "duplicate"
    # The rotation off while the board's position (the translation of the residual) is not:
    # the planar-target pose ambiguity.
    E = dq.mul(dq.mul(dq.mul(dq.inv(fit.Z), p.A[k]), fit.X), p.C[k])
    t = dq.to_pose(E)[1]
    St = S[3:, 3:]
    pos_nis = float(t @ np.linalg.solve(St, t))
    ang = float(np.linalg.norm(r[:3]))
    if ang > np.radians(3.0) and pos_nis <= _GATE_3:
        return (f"marker flip? rotation off by {np.degrees(ang):.1f}° while the board's "
                f"position agrees to {1e3 * np.linalg.norm(t):.2f} mm")
    return (f"NIS {nis:.3g} > {_GATE_6:.3g}: off by {np.degrees(ang):.2f}° / "
            f"{1e3 * np.linalg.norm(t):.2f} mm")
