"""Other readings of the data: the setup swapped or the camera poses inverted (refused when they
fit far better than the reading given), and the two that fit (nearly) as well as the right one,
so that the residuals cannot refuse them and only plausibility tells: both poses inverted
(``T_flange_base`` and ``T_target_camera``: ``F⁻¹ Z C⁻¹ = X``, X and Z exchanged) and the
camera's translations at another scale (a wrong board size).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from dqpose import dq, lie
from dqpose.errors import Infeasible
from dqpose.handeye.closed_form import _closed_form
from dqpose.handeye.setups import EYE_IN_HAND, _other, _reading

if TYPE_CHECKING:
    from dqpose.handeye.checks import _Prepared
    from dqpose.handeye.likelihood import _Fit

_READING_FACTOR = 5.0                  # another reading fits this many times better: refuse
_MAX_MOUNT = 1.0                       # (m) a flange-mounted camera or target farther, or
_MIN_FIXED = 0.25                      # (m) a fixed one nearer the base's origin: warn
                                       # (only when both poses inverted would be plausible)
# Camera translations scaled beyond both: re-solved rescaled, with a warning. A Wald test at 5 σ
# (nominal false-alarm rate < 1e-6 a solve; none in 800 healthy scenes of
# tests/bench/bench_handeye_false_alarms.py).
_SCALE_SIGMAS, _MIN_SCALE = 5.0, 2e-3


def _spread(A, C, X, Z, use):
    """Median rotation (rad) and position (m) of the per-sample ``A_i X C_i`` about ``Z``."""
    E = dq.mul(dq.mul(dq.mul(dq.inv(Z), A[use]), X), C[use])
    ang = 2.0 * np.arctan2(np.linalg.norm(E[:, 1:4], axis=1), np.abs(E[:, 0]))
    pos = np.linalg.norm(dq.to_pose(E)[1], axis=1)
    return float(np.median(ang)), float(np.median(pos))


def _compare_readings(F, A, C, setup, use, closed, s_th, s_d) -> tuple:
    """``(reading, median rad, median m)`` of the closed form's fit of the reading given
    (``closed``), the setup swapped and the camera poses inverted, over the samples ``use``;
    ``Infeasible`` when another fits far better (``s_th``, ``s_d``: the robust σ of the motions'
    angle and pitch differences). Both swapped is no alternative: ``F⁻¹ Z C⁻¹ = X`` is the same
    equation with X and Z exchanged."""
    readings = []
    other = _other(setup)
    for name, Ar, Cr in ((setup, A, C),
                         (other, _reading(F, other), C),
                         (f"{setup}, camera_target inverted", A, dq.inv(C))):
        res = closed if Ar is A and Cr is C else _closed_form(Ar, Cr, use)
        if res is None:
            continue
        readings.append((name,) + _spread(Ar, Cr, res[0], res[1], use))
    given = readings[0]
    best = min(readings[1:], key=lambda r: r[1] / s_th + r[2] / s_d, default=None)
    if best is not None and (given[1] > _READING_FACTOR * best[1] + np.radians(0.05)
                             and given[2] > _READING_FACTOR * best[2] + 1e-3):
        hint = ("the setup is swapped, or base_flange holds T_flange_base"
                if "inverted" not in best[0] else
                "camera_target holds T_target_camera" if best[0].startswith(setup) else
                "the setup is swapped and camera_target holds T_target_camera")
        raise Infeasible(f"base_flange, camera_target: the data fit {best[0]} far better than "
                         f"{setup} as given (median residual {np.degrees(best[1]):.3g}° / "
                         f"{1e3 * best[2]:.3g} mm against {np.degrees(given[1]):.3g}° / "
                         f"{1e3 * given[2]:.3g} mm): {hint}?")
    return tuple(readings)


@dataclass(frozen=True)
class _Reading:
    reach_ok: bool    # the flange-mounted part near the flange
    base_ok: bool     # the fixed part off the base
    front: bool       # the target in front of the camera (z > 0 in T_camera_target), every sample
    behind: bool      # ... behind it in every sample
    says: str

    @property
    def mount_ok(self) -> bool:
        return self.reach_ok and self.base_ok


def _plausible(p: _Prepared, X, Z, inlier, inverted: bool = False) -> _Reading:
    """How plausible the answer ``(X, Z)`` is as a mount (``inverted``: the reading of both poses
    inverted, where ``(Z, X)`` of the given fit is the answer and ``C⁻¹`` the camera poses)."""
    mount, fixed = (X, Z) if p.setup == EYE_IN_HAND else (Z, X)
    reach = float(np.linalg.norm(dq.to_pose(mount)[1]))
    base = float(np.linalg.norm(dq.to_pose(fixed)[1]))
    C = p.C[inlier]
    depth = dq.to_pose(dq.inv(C) if inverted else C)[1][:, 2]
    what = ("camera", "target") if p.setup == EYE_IN_HAND else ("target", "camera")
    return _Reading(reach <= _MAX_MOUNT, base >= _MIN_FIXED, bool(np.all(depth > 0.0)),
                    bool(np.all(depth < 0.0)),
                    f"the {what[0]} comes out {reach:.2f} m from the flange and the {what[1]} "
                    f"{base:.2f} m from the robot base")


def _inverse_noise(T, S):
    return None if S is None else lie.cov_inverse(T, S)


def _moved(a, b) -> float:
    return float(np.linalg.norm(dq.to_pose(a)[1] - dq.to_pose(b)[1]))


def _camera_scale(fit: _Fit, C: np.ndarray) -> tuple[float, float, np.ndarray]:
    """The scale ``λ`` of the camera's translations that fits best, its σ, and what ``λ`` free
    adds to the covariance of ``(X, Z)``: one Gauss–Newton step from λ = 1 at the optimum with
    ``λ`` joined to (X, Z). Scaling ``t`` of ``C_i`` moves
    ``C_i`` by ``Exp([0, R_iᵀ t_i dλ])`` on the right, so the residual by ``Jr⁻¹(r_i)`` of that."""
    R, t = (M := dq.to_matrix(C))[:, :3, :3], M[:, :3, 3]
    d = np.zeros((len(C), 6))
    d[:, 3:] = (np.swapaxes(R, 1, 2) @ t[..., None])[..., 0]
    Jl = (lie.se3_right_jacobian_inv(fit.r) @ d[..., None])[..., 0]          # (n, 6)
    W = np.linalg.inv(fit.S)
    Jfull = np.concatenate([fit.J, Jl[..., None]], axis=2)                   # (n, 6, 13)
    JtW = np.swapaxes(Jfull, 1, 2) @ W
    H = (JtW @ Jfull).sum(axis=0)
    g = np.einsum("nij,nj->i", JtW, fit.r)
    try:
        Hi = np.linalg.inv(H)
    except np.linalg.LinAlgError:
        return 1.0, float("inf"), np.zeros((12, 12))
    step = -Hi @ g
    # λ's σ is the larger of the model's, (H⁻¹)_λλ, and the sandwich's, (H⁻¹ Σ gᵢgᵢᵀ H⁻¹)_λλ
    # (gᵢ each sample's score): the scale moves the camera's translations along its line of
    # sight, where a detector's depth noise is largest, and isotropic noise (estimated, or a
    # covariance given too small) understates it there. KinHEC's camera, 3× noisier in depth,
    # had its scale "corrected" to 0.57–0.97 in 9 of ~920 healthy sequences; the sandwich holds
    # to the scatter the residuals show whatever the model.
    # (the scores at the λ-free optimum, one Gauss–Newton step on: at λ = 1 a real scale error
    # is a shared bias of every score, not scatter)
    gi = np.einsum("nij,nj->ni", JtW, fit.r + np.einsum("nij,j->ni", Jfull, step))
    sandwich = Hi @ (gi.T @ gi) @ Hi
    sigma = float(np.sqrt(max(Hi[12, 12], sandwich[12, 12], 0.0)))
    if not np.isfinite(sigma):
        return 1.0 + float(step[12]), float("inf"), np.zeros((12, 12))
    # λ free widens (X, Z)'s covariance from H₁₂⁻¹ to (H⁻¹)₁₂: by h hᵀ / (H⁻¹)_λλ, h = (H⁻¹)_:12,λ.
    h = Hi[:12, 12]
    extra = np.outer(h, h) / Hi[12, 12] if Hi[12, 12] > 0.0 else np.zeros((12, 12))
    return 1.0 + float(step[12]), sigma, extra
