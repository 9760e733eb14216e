"""The camera's translations at another scale than the robot's (a wrong board size, a monocular
camera): the scale that fits best with its σ, and the evidence for it against no scale error.

A rescale needs a likelihood ratio of the fit at the best-fitting scale against the fit at 1
above ``SCALE_SIGMAS²`` (χ²₁; scaled by the model's variance over the sandwich's when the
residuals scatter more than the model says: the robust likelihood ratio). It is computed (one
more fit) only when the scale is off 1 by more than ``SCREEN_SIGMAS`` of its σ (the larger of
the model's and the sandwich's): at 1 that σ is inflated by the misfit of a real scale error
(twice the scale with the noise estimated: 0.77 ± 0.055 in one step), so a Wald test at 5 σ
missed it. Without the evidence
the answer is the unscaled fit's, the scale and its σ still reported. The likelihood is that of
the translations as measured (:func:`camera_scale`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dqpose import dq, lie
from dqpose.handeye.likelihood import Fit, gauss_newton
from dqpose.handeye.noise import Noise

# The likelihood-ratio threshold (5 σ: nominal false-alarm rate < 1e-6 a solve), the screen before
# it, and the smallest scale error corrected.
SCALE_SIGMAS, SCREEN_SIGMAS, MIN_SCALE = 5.0, 2.0, 2e-3


@dataclass(frozen=True)
class _Scale:
    lam: float            # the best-fitting scale
    sigma: float          # its σ: the larger of the model's and the sandwich's
    model_sigma: float    # the model's alone, (H⁻¹)_λλ^½
    extra: np.ndarray     # (12, 12): what λ free adds to the covariance of (X, Z)


def camera_scale(fit: Fit, C: np.ndarray, noise: Noise, use: np.ndarray) -> _Scale:
    """The scale ``λ`` of the camera's translations that fits best, its σ, and what ``λ`` free
    adds to the covariance of ``(X, Z)``: one Newton step from λ = 1 at the optimum with ``λ``
    joined to (X, Z), ``C`` the samples ``use`` of the fit. Scaling ``t`` of ``C_i`` moves
    ``C_i`` by ``Exp([0, R_iᵀ t_i dλ])`` on the right, so the residual by ``Jr⁻¹(r_i)`` of that.

    The likelihood is that of the translations as measured: the residuals of translations
    scaled by λ carry their noise scaled by λ too, and the density of the measured ones is the
    scaled ones' times ``λ³`` a sample. Both terms of the score at λ = 1: ``+3`` a sample (the
    Jacobian) and, with the noise given, ``−½ tr(S⁻¹Ṡ) + ½ rᵀS⁻¹ṠS⁻¹r`` (``Ṡ`` the change of
    the residual covariance as the camera's translation noise scales; with it estimated the noise
    is profiled out, which leaves the Jacobian alone). Without them shrinking the translations
    shrank their noise and read as a better fit: at KinHEC's camera noise c5 (depth 40 mm a view)
    the likelihood peaked at λ = 0.91 ± 0.017 on data with no scale error."""
    R, t = (M := dq.to_matrix(C))[:, :3, :3], M[:, :3, 3]
    n = len(C)
    d = np.zeros((n, 6))
    d[:, 3:] = (np.swapaxes(R, 1, 2) @ t[..., None])[..., 0]
    Jri = lie.se3_right_jacobian_inv(fit.r)
    Jl = (Jri @ d[..., None])[..., 0]                                       # (n, 6)
    W = np.linalg.inv(fit.S)
    Jfull = np.concatenate([fit.J, Jl[..., None]], axis=2)                   # (n, 6, 13)
    JtW = np.swapaxes(Jfull, 1, 2) @ W
    H = (JtW @ Jfull).sum(axis=0)
    gi = np.einsum("nij,nj->ni", JtW, fit.r)        # each sample's gradient of ½ rᵀWr
    gi[:, 12] -= 3.0 + _noise_score(fit, W, Jri, noise, use)
    g = gi.sum(axis=0)
    try:
        Hi = np.linalg.inv(H)
    except np.linalg.LinAlgError:
        return _Scale(1.0, float("inf"), float("inf"), np.zeros((12, 12)))
    step = -Hi @ g
    # λ's σ is the larger of the model's, (H⁻¹)_λλ, and the sandwich's, (H⁻¹ Σ gᵢgᵢᵀ H⁻¹)_λλ
    # (gᵢ each sample's score at the λ-free optimum, one step on: at λ = 1 a real scale error is
    # a shared bias of every score, not scatter): the scale moves the camera's translations along
    # its line of sight, where a detector's depth noise is largest, and an isotropic noise
    # (estimated, or a covariance given too small) understates it there.
    gi = gi + np.einsum("nik,nkj,j->ni", JtW, Jfull, step)
    sandwich = Hi @ (gi.T @ gi) @ Hi
    sigma = float(np.sqrt(max(Hi[12, 12], sandwich[12, 12], 0.0)))
    model = float(np.sqrt(max(Hi[12, 12], 0.0)))
    if not np.isfinite(sigma):
        return _Scale(1.0 + float(step[12]), float("inf"), float("inf"), np.zeros((12, 12)))
    # λ free widens (X, Z)'s covariance from H₁₂⁻¹ to (H⁻¹)₁₂: by h hᵀ / (H⁻¹)_λλ, h = (H⁻¹)_:12,λ.
    h = Hi[:12, 12]
    extra = np.outer(h, h) / Hi[12, 12] if Hi[12, 12] > 0.0 else np.zeros((12, 12))
    return _Scale(1.0 + float(step[12]), sigma, model, extra)


def _noise_score(fit: Fit, W, Jri, noise: Noise, use) -> np.ndarray | float:
    """Each sample's ``−½ tr(S⁻¹Ṡ) + ½ rᵀS⁻¹ṠS⁻¹r`` at λ = 1 with the camera noise given
    (``Ṡ`` the residual covariance's change as the camera's translation noise scales with λ:
    ``Σ_C → D Σ_C D``, ``D = diag(1, 1, 1, λ, λ, λ)``); 0 with the noise estimated."""
    if noise.estimate:
        return 0.0
    E = np.diag([0.0] * 3 + [1.0] * 3)
    SC = noise.SC[use]
    Sdot = Jri @ (E @ SC + SC @ E) @ np.swapaxes(Jri, 1, 2)
    y = np.einsum("nij,nj->ni", W, fit.r)
    return (-0.5 * np.einsum("nij,nji->n", W, Sdot)
            + 0.5 * np.einsum("ni,nij,nj->n", y, Sdot, y))


def _log_likelihood(fit: Fit, lam: float) -> float:
    """The Gaussian log-likelihood of the measured data at a fit on translations scaled by
    ``lam``: ``−½ Σ (log det S_i + r_iᵀ S_i⁻¹ r_i) + 3 n log λ`` (the Jacobian of the scaling)."""
    _, logdet = np.linalg.slogdet(fit.S)
    quad = np.einsum("ni,nij,nj->", fit.r, np.linalg.inv(fit.S), fit.r)
    return float(-0.5 * (logdet.sum() + quad) + 3.0 * len(fit.r) * np.log(lam))


def evidence(p, fit: Fit, noise: Noise, use, scale: _Scale) -> float:
    """The (robust) likelihood ratio of the fit at ``scale.lam`` against ``fit`` at 1, on the same
    samples ``use``: ``2 (ℓ(λ) − ℓ(1))``, times ``σ_model² / σ²`` (≤ 1: the residuals scatter
    more along the scale than the model says, so its likelihood overstates the evidence)."""
    lam = scale.lam
    if not lam > 0.0:
        return 0.0
    C = p.C.copy()
    C[:, 4:] *= lam             # the dual part carries the translation linearly
    SC = noise.SC
    if SC is not None:
        D = np.diag([1.0] * 3 + [lam] * 3)
        SC = D @ SC @ D
    scaled = gauss_newton(p.A, C, fit.X, fit.Z,
                          Noise(noise.SA, SC, noise.estimate, noise.frames), use)
    lr = 2.0 * (_log_likelihood(scaled, lam) - _log_likelihood(fit, 1.0))
    return lr * min(1.0, (scale.model_sigma / scale.sigma) ** 2)
