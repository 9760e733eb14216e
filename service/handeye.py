"""Hand-eye calibration: robot and camera poses in, the camera's mount with an honest covariance out.

Conventions (the rest of dqpose's, :mod:`dqpose.dq` and :mod:`dqpose.lie`):

* ``base_flange`` are the robot's ``T_base_flange`` ``(n, 8)``; ``camera_target`` the detector's
  ``T_camera_target`` ``(n, 8)``; sample i is the pair of row i of each.
* **eye_in_hand** (camera on the flange): ``x = T_flange_camera``, ``z = T_base_target``, and every
  sample satisfies ``base_flange_i · x · camera_target_i = z``.
  **eye_to_hand** (camera fixed, target on the flange): ``x = T_base_camera``,
  ``z = T_flange_target``, and ``base_flange_i⁻¹ · x · camera_target_i = z``. Eye-to-hand is solved
  as eye-in-hand on the inverted flange poses ``A_i = base_flange_i⁻¹``; everything below is
  written for ``A_i · X · C_i = Z`` (``C_i = camera_target_i``), the robot-world-hand-eye form on
  absolute poses.
* Covariances are 6×6, rotation first ``[ωx ωy ωz vx vy vz]``, of a right (body-frame)
  perturbation ``T · Exp(ξ)`` with the SE(3) exponential: GTSAM's ``Pose3`` convention, the one
  of :mod:`dqpose.fusion`. A noise covariance given for the poses uses it too (robot: the
  perturbation of ``T_base_flange``; camera: of ``T_camera_target``).

The solution, in order:

1. **Closed form** (Daniilidis 1999, dual quaternions): motions between all pairs ``i < j``
   (not only consecutive ones), ``A_j⁻¹A_i · X = X · C_j C_i⁻¹``; each pair's dual quaternions put
   in one hemisphere (scalar parts ≥ 0, the short screw both sides); pairs that rotate less than
   ``_MIN_PAIR_ANGLE`` or nearly half a turn (sign ill-defined) left out, and samples whose pairs
   are not screw-congruent (rotation angle and pitch of the two motions must agree) left out of
   it; the 6 m × 8 system solved by SVD, then re-solved with Huber weights on each pair's
   residual (robust averaging). ``Z`` is then the DIB mean (:func:`dqpose.dq.dib`) of the
   per-sample estimates ``A_i X C_i``.
2. **Maximum likelihood** on ``(X, Z)``: Gauss–Newton on SE(3)×SE(3) with right perturbations
   and exact Jacobians (:mod:`dqpose.lie`) of the residuals ``r_i = Log(Z⁻¹ A_i X C_i)``. Noise on
   both the robot and the camera poses enters through each residual's covariance
   ``Σ_r,i = Jr⁻¹(r_i) (Ad(K_i⁻¹) Σ_A,i Ad(K_i⁻¹)ᵀ + Σ_C,i) Jr⁻ᵀ``, ``K_i = X C_i``
   (the errors-in-variables problem with the true poses eliminated, to first order), re-evaluated
   at each iterate. The noise covariances are the caller's when given (``noise_model == "given"``),
   else **estimated from the residuals** (``"estimated"``, :class:`_Noise`): three isotropic
   variance components, camera rotation, translation (camera and robot alike) and robot rotation
   (which reaches the residual's translation through the lever arm ``X C_i``), by REML Fisher
   scoring at every iterate, the 12 fitted degrees of freedom taken out by leverage. The
   covariance of ``(X, Z)`` is the inverse of the information ``Σ Jᵢᵀ Σ_r,i⁻¹ Jᵢ`` at the
   optimum; ``covariance_x``/``covariance_z`` are its marginals. With the noise estimated, the
   uncertainty of the estimate is propagated into them (Kenward–Roger,
   :meth:`_Noise.kenward_roger`): from 10 poses the bare ``H(θ̂)⁻¹`` had mean NEES 6.7–9.3; with
   it 5.6–6.8 over 200 seeded trials on every row of tests/bench/bench_handeye.py (5.7–6.3 at
   20 poses).
3. **Outliers**: every sample is gated on its NIS (χ² with 6 dof, probability ``_GATE``):
   the inliers' standardised residual ``r_iᵀ (Σ_r,i − J_i P J_iᵀ)⁻¹ r_i`` (the leave-one-out
   NIS to first order), the others' against the prediction ``Σ_r,i + J_i P J_iᵀ``, starting
   from a fit on the samples that pass the screw-congruence test and re-fitting until the set
   settles. ``robust`` leaves the outliers out (``rejected``, each with a reason: a marker flip
   when the rotation is off and the board's position is not); otherwise they stay in and a
   warning names them.
4. **After solving**: leave-one-out (how far X moves when each sample is left out, to first
   order: ``P J_iᵀ S_i⁻¹ r_i``), the closed form's distance from the answer in its own
   covariance, and :func:`next_best_pose`.
5. **Corner level** (``corners`` given): maximum likelihood on the reprojection of the board's
   corners through ``C_i = X⁻¹ A_i⁻¹ Z`` (:func:`_corner_fit`), from the pose-level answer, with
   an optional focal-length scale and a correction of each robot pose under the robot's noise,
   given or estimated (taken as exact, 0.02° / 0.1 mm of robot noise made the covariance claim
   ~20× too much; modelled, mean NEES 5.3–6.3). The corner noise is estimated per view: among
   rendered views of one scene it ranges 0.02–0.1 px, and one σ for all had the covariance
   of X claim too much end to end (mean NEES 9.6 over 50 trials; per view 7.6 over 200). The
   rest of that 7.6 was the detector's: OpenCV's ChArUco corners shared an error within each
   view, which independent corner noise cannot describe; drivers/camera.py now refines them
   off the markers, and end to end the mean NEES is 5.5–5.7 (three seeds of 200 trials).

Data checks (:func:`check` and :func:`calibrate`): malformed input is a
:class:`~dqpose.errors.FieldError` naming the argument and index; unusable data an
:class:`~dqpose.errors.Infeasible` naming the reason and the samples (fewer than 3 distinct
poses, no rotation between samples, rotation axes all parallel, poses that do not correspond,
millimetres given as metres, the data fitting another reading far better: setup swapped or a pose
convention inverted); anything doubtful but solvable a warning naming the samples (duplicates,
stale poses, small or nearly parallel rotations, samples not screw-congruent, outliers).

Two readings fit (nearly) as well as the right one, so the residuals cannot refuse them, and
answering them as given would be silently wrong (:func:`_calibrate`):

* **Both poses inverted** (``T_flange_base`` and ``T_target_camera``) fits exactly as well as
  the truth, X and Z exchanged (``F⁻¹ Z C⁻¹ = X``). Plausibility tells: a flange-mounted part
  within ``_MAX_MOUNT`` of the flange, a fixed one ``_MIN_FIXED`` off the base, and the target in
  front of the camera (``z > 0`` in ``T_camera_target``; inverted, the camera's position in the
  board's frame, whose sign depends on the board's convention). When the mount is implausible as
  given and plausible inverted and the depths agree with the inverted reading, the answer is the
  inverted reading's, with a warning; when the depths do not tell, ``Infeasible`` naming both.
* **The camera's translations at another scale** (a wrong board size, :func:`_camera_scale`):
  the data are re-solved with the camera's translations (and at corner level the board's points)
  scaled by the best-fitting scale, whose uncertainty enters the covariance (at corner level the
  board's scale is refined with the corners), with a warning naming the scale.

Healthy scenes (960 runs over tests/_handeye.py's grid) are never refused.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import NamedTuple, Optional

import numpy as np

from dqpose import dq, fusion, lie
from dqpose.errors import FieldError, Infeasible, rename

__all__ = ["SETUPS", "Calibration", "Rejection", "calibrate", "check", "flange_for", "next_best_pose",
           "view_at"]

SETUPS = ("eye_in_hand", "eye_to_hand")

_MIN_POSES = 3
_MIN_PAIR_ANGLE = np.radians(2.0)      # pairs rotating less say little about X's rotation
_MAX_PAIR_ANGLE = np.radians(170.0)    # near half a turn the hemisphere of a pair is ambiguous
_DUPLICATE_ANGLE = np.radians(1e-3)    # two samples this close in rotation and translation
_DUPLICATE_DISTANCE = 1e-6             # (m) on both sides are one sample taken twice
_PURE_TRANSLATION = np.radians(0.5)    # no pair rotates more: X's translation is not determined
_SMALL_ROTATION = np.radians(10.0)     # warn when no pair rotates more than this
_MIN_EXCITATION = np.radians(0.5)      # smallest rotation excitation: below it, axes parallel
_LOW_EXCITATION = np.radians(3.0)      # warn below this (a healthy wrist set: ~15–30°)
_GATE = 0.999                          # χ² probability of the robust gate
_GATE_6 = 22.457744484825192           # χ²₆ quantile at _GATE (fusion.chi2_quantile(0.999, 6))
_GATE_3 = 16.266236196238010           # χ²₃ quantile at _GATE
_SUSPECT = 4.0                         # a sample whose median congruence error is this many σ off
_MISMATCH_ANGLE = np.radians(3.0)      # median congruence errors beyond these: poses do not
_MISMATCH_PITCH = 0.02                 # correspond (time or pairing), for most samples (m)
_READING_FACTOR = 5.0                  # another reading fits this many times better: refuse
_MAX_MOUNT = 1.0                       # (m) a flange-mounted camera or target farther, or
_MIN_FIXED = 0.25                      # (m) a fixed one nearer the base's origin: warn
_SCALE_SIGMAS, _MIN_SCALE = 5.0, 2e-3  # camera translations scaled beyond both: warn
_FLOORS = np.array([1e-9, 1e-9, 1e-12]) ** 2   # smallest estimated variances: exact data
_TOL = 1e-8                            # a step this short in its own σ (squared): converged
_MAX_ITER = 30


@dataclass(frozen=True)
class Rejection:
    """A sample the χ² gate flagged, and why (left out in robust mode)."""
    index: int
    reason: str


@dataclass(frozen=True)
class Calibration:
    setup: str
    x: np.ndarray             # (8,) eye_in_hand: T_flange_camera; eye_to_hand: T_base_camera
    z: np.ndarray             # (8,) eye_in_hand: T_base_target;  eye_to_hand: T_flange_target
    covariance_x: np.ndarray  # (6,6) rotation first, right perturbation T·Exp(ξ) (GTSAM Pose3)
    covariance_z: np.ndarray  # (6,6) same convention
    residuals: np.ndarray     # (n,2) per sample: rotation (rad), then the target's position (m)
    warnings: tuple[str, ...]
    inliers: np.ndarray = field(default=None)            # (n,) bool: samples in the answer
    rejected: tuple[Rejection, ...] = ()
    covariance: np.ndarray = field(default=None)         # (12,12) joint, [X; Z]
    information: np.ndarray = field(default=None)        # (12,12) its inverse, for next_best_pose
    noise_model: str = "estimated"                       # "given" or "estimated"
    camera_covariance: np.ndarray = field(default=None)  # (6,6) or (n,6,6) as used
    robot_covariance: Optional[np.ndarray] = None        # (6,6), (n,6,6) or None (exact robot)
    residual_covariance: np.ndarray = field(default=None)  # (n,6,6) Σ_r,i at the optimum
    nis: np.ndarray = field(default=None)                # (n,) standardised residual, χ²₆
    leave_one_out: np.ndarray = field(default=None)      # (n,2) X moves (rad, m) without each
    closed_form_x: np.ndarray = field(default=None)      # (8,) the closed form's X
    closed_form_z: np.ndarray = field(default=None)
    agreement: tuple[float, float, float] = (0.0, 0.0, 0.0)  # closed form vs X: rad, m, NEES
    rotation_condition: float = 0.0     # condition number of the rotation information
    excitation: float = 0.0             # its smallest eigenvalue as an RMS angle (rad)
    iterations: int = 0
    readings: tuple[tuple[str, float, float], ...] = ()  # (reading, median rad, median m)
    reprojection: Optional[np.ndarray] = None  # (n,) RMS px per view, when corners were given
    focal_scale: float = 1.0            # the focal lengths' refined scale (refine_focal)
    focal_sigma: float = 0.0            # its standard deviation
    pixel_sigma: float = 0.0            # corner noise (px), given or estimated
    camera_scale: tuple[float, float] = (1.0, 0.0)  # best scale of the camera's translations, σ


# ---- input -------------------------------------------------------------------------------------
def _poses(x, name: str) -> np.ndarray:
    try:
        a = fusion._finite(x, name, (8,), None)   # shape and finiteness, with the index
        dq.to_matrix(a)                           # the core's unit and rigidity checks
    except ValueError as e:
        raise rename(e, {"a": name + "{}"}) from None
    return dq.normalize(a)


def _setup(setup) -> str:
    if setup not in SETUPS:
        raise FieldError(f"setup: expected one of {', '.join(SETUPS)}, got {setup!r}")
    return setup


def _noise(cov, name: str, n: int) -> Optional[np.ndarray]:
    if cov is None:
        return None
    try:
        S = np.asarray(cov, dtype=np.float64)
    except (TypeError, ValueError):
        raise FieldError(f"{name}: expected numbers, got {type(cov).__name__}") from None
    if S.shape not in ((6, 6), (n, 6, 6)):
        raise FieldError(f"{name}: expected shape (6, 6) or ({n}, 6, 6), got {S.shape}")
    S = np.broadcast_to(S, (n, 6, 6))
    for i in range(n if S.ndim == 3 and np.shape(cov) != (6, 6) else 1):
        s = S[i]
        where = f"{name}[{i}]" if np.shape(cov) != (6, 6) else name
        if not np.all(np.isfinite(s)):
            raise FieldError(f"{where}: contains NaN or infinity")
        if not np.allclose(s, s.T, rtol=1e-9, atol=0.0):
            raise FieldError(f"{where}: not symmetric")
        if np.linalg.eigvalsh(0.5 * (s + s.T))[0] < 0.0:
            raise FieldError(f"{where}: not positive semi-definite")
        var = np.diagonal(s)
        bad = (var > 0.0) & ~((var >= fusion._MIN_VARIANCE) & (var <= fusion._MAX_VARIANCE))
        if bad.any():
            raise FieldError(f"{where}: variance {var[bad][0]:.6g} outside "
                             f"[{fusion._MIN_VARIANCE:g}, {fusion._MAX_VARIANCE:g}] (0 is "
                             f"exact): its information cannot be used")
    return 0.5 * (S + np.swapaxes(S, -1, -2))


def _samples(idx) -> str:
    idx = [int(i) for i in idx]
    return f"sample{'s' if len(idx) != 1 else ''} {', '.join(map(str, idx))}"


# ---- closed form -------------------------------------------------------------------------------
def _hemisphere(d: np.ndarray) -> np.ndarray:
    return np.where(d[..., :1] < 0.0, -d, d)


def _motions(A, C, i, j):
    """The pair motions ``A_j⁻¹ A_i`` and ``C_j C_i⁻¹`` in one hemisphere each."""
    a = _hemisphere(dq.mul(dq.inv(A[j]), A[i]))
    b = _hemisphere(dq.mul(C[j], dq.inv(C[i])))
    return a, b


def _rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
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
    v1, v2 = Vt[-2], Vt[-1]
    u1, d1, u2, d2 = v1[:4], v1[4:], v2[:4], v2[4:]
    # (λ1, λ2) with q·q' = 0: a quadratic form M in (λ1, λ2); its null directions, the one with
    # the larger |q| (the other is the pure-dual, translation-only solution).
    M = np.array([[u1 @ d1, 0.5 * (u1 @ d2 + u2 @ d1)], [0.5 * (u1 @ d2 + u2 @ d1), u2 @ d2]])
    N = np.array([[u1 @ u1, u1 @ u2], [u1 @ u2, u2 @ u2]])
    e, R = np.linalg.eigh(M)
    if e[0] * e[1] < 0.0:
        c = np.sqrt(np.abs(e[::-1]))           # directions where e0 y0² + e1 y1² = 0
        cands = [R @ np.array([c[0], c[1]]), R @ np.array([c[0], -c[1]])]
    else:                                      # noise: the nearest direction to a root
        cands = [R[:, int(np.argmin(np.abs(e)))]]
    lam = max(cands, key=lambda l: l @ N @ l)
    lam = lam / np.sqrt(lam @ N @ lam)
    x = lam[0] * v1 + lam[1] * v2
    return dq.normalize(_hemisphere(x))


def _closed_form(A, C, use: np.ndarray, robust: bool = True):
    """Daniilidis over all usable pairs, Huber-reweighted; ``Z`` the DIB mean of ``A_i X C_i``.
    Returns ``(X, Z, number of pairs)``, or None when too few pairs rotate."""
    idx = np.flatnonzero(use)
    i, j = np.triu_indices(len(idx), 1)
    i, j = idx[i], idx[j]
    a, b = _motions(A, C, i, j)
    ang = 2.0 * np.arccos(np.clip(a[:, 0], -1.0, 1.0))
    keep = (ang > _MIN_PAIR_ANGLE) & (ang < _MAX_PAIR_ANGLE)
    if np.count_nonzero(keep) < 2:
        return None
    a, b = a[keep], b[keep]
    T = _rows(a, b)
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


# ---- screw congruence --------------------------------------------------------------------------
@dataclass
class _Congruence:
    i: np.ndarray
    j: np.ndarray
    angle_a: np.ndarray
    angle_b: np.ndarray
    pitch_a: np.ndarray
    pitch_b: np.ndarray


def _congruence(A, C) -> _Congruence:
    n = A.shape[0]
    i, j = np.triu_indices(n, 1)
    a, b = _motions(A, C, i, j)
    sa, sb = dq.screw(a), dq.screw(b)
    return _Congruence(i, j, sa.theta, sb.theta, sa.d, sb.d)


def _per_sample_median(n, i, j, v) -> np.ndarray:
    """Per sample, the median of ``v`` over the pairs it is in."""
    M = np.full((n, n), np.nan)
    M[i, j] = v
    M[j, i] = v
    out = np.zeros(n)
    seen = ~np.all(np.isnan(M), axis=1)
    out[seen] = np.nanmedian(M[seen], axis=1)
    return out


# ---- the model ---------------------------------------------------------------------------------
def _transported(X, C, SA, SC, Jri):
    """Σ_r,i = Jr⁻¹(r) (Ad(K⁻¹) Σ_A Ad(K⁻¹)ᵀ + Σ_C) Jr⁻ᵀ, K = X C_i (see the module docstring)."""
    S = SC.copy() if SC is not None else np.zeros((C.shape[0], 6, 6))
    if SA is not None:
        S = S + lie.cov_left_to_right(dq.mul(X, C), SA)
    return Jri @ S @ np.swapaxes(Jri, -1, -2)


def _evaluate(A, C, X, Z):
    E = dq.mul(dq.mul(dq.mul(dq.inv(Z), A), X), C)
    return E, lie.se3_log(E)


@dataclass
class _Fit:
    X: np.ndarray
    Z: np.ndarray
    E: np.ndarray
    r: np.ndarray
    J: np.ndarray      # (n,6,12) d r_i / d(δx, δz)
    S: np.ndarray      # (n,6,6) residual covariances
    H: np.ndarray      # (12,12) information
    P: np.ndarray      # (12,12) covariance at the noise as estimated or given
    iterations: int
    reported: np.ndarray   # (12,12) P with the noise estimate's uncertainty (Kenward–Roger)


_ROT, _TRANS = np.diag([1.0] * 3 + [0.0] * 3), np.diag([0.0] * 3 + [1.0] * 3)


class _Noise:
    """The residual covariances ``Σ_r,i``: transported from the given pose noise, or estimated.

    Estimated (no covariance given): three isotropic variance components, camera rotation
    ``θ₁``, translation ``θ₂`` (the camera's and the robot's: isotropic translation noise on
    either pose reaches the residual identically) and robot rotation ``θ₃``, transported like a
    given robot noise (it reaches the residual's translation through the lever arm ``X C_i``,
    which is what tells it from the camera's). ``Σ_r,i = Σ θ_k G_k,i``; the θ are re-estimated
    at every Gauss–Newton iterate by the iterated variance-component (REML) update
    ``θ_k ← θ_k · Σ rᵢᵀWᵢG_kWᵢrᵢ / (Σ tr(WᵢG_k) − tr(P Σ JᵢᵀWᵢG_kWᵢJᵢ))``, which keeps them
    positive and takes the 12 fitted degrees of freedom out by leverage (:meth:`update`)."""

    def __init__(self, SA, SC, estimate: bool, robot_frames: Optional[np.ndarray] = None):
        self.SA, self.SC, self.estimate = SA, SC, estimate
        self.frames = robot_frames            # Ad(F_i) for eye_to_hand (A = F⁻¹), else None
        self.theta: Optional[np.ndarray] = None
        self.step: Optional[np.ndarray] = None
        self.G: Optional[np.ndarray] = None   # (n, 3, 6, 6) at the last evaluation

    def components(self, X, C, Jri, use) -> np.ndarray:
        n = len(C)
        rot = _ROT if self.frames is None else self.frames[use] @ _ROT @ np.swapaxes(
            self.frames[use], 1, 2)
        G = np.empty((n, 3, 6, 6))
        G[:, 0], G[:, 1] = _ROT, _TRANS
        G[:, 2] = lie.cov_left_to_right(dq.mul(X, C), np.broadcast_to(rot, (n, 6, 6)))
        if Jri is not None:
            G = Jri[:, None] @ G @ np.swapaxes(Jri, 1, 2)[:, None]
        return G

    def __call__(self, X, C, r, Jri, use=None) -> np.ndarray:
        if self.estimate:
            self.G = self.components(X, C, Jri, use)
            if self.theta is None:
                v = (1.4826 * np.median(np.abs(r), axis=0)) ** 2   # outliers do not inflate it
                self.theta = np.array([v[:3].mean(), v[3:].mean(), 0.1 * v[:3].mean()])
                self.theta = np.maximum(self.theta, _FLOORS)
            return np.einsum("k,nkij->nij", self.theta, self.G)
        SA = None if self.SA is None else self.SA[use]
        return _transported(X, C, SA, self.SC[use], Jri)

    def _reml(self, J: np.ndarray, P: np.ndarray):
        """The pieces of the REML score and information at the current ``θ``: ``W_i = Σ_r,i⁻¹``,
        ``B_i = W_i J_i``, ``M_k = Σ B_iᵀ G_k,i B_i`` (12×12, ``−∂H/∂θ_k``),
        ``Q_kl = Σ B_iᵀ G_k,i W_i G_l,i B_i`` and ``F_kl = tr(R G_k R G_l)`` (twice the REML
        information), ``R = W − W J P Jᵀ W``: every trace expanded over the blocks, so nothing
        6n × 6n is formed."""
        G = self.G
        W = np.linalg.inv(np.einsum("k,nkij->nij", self.theta, G))
        B = W @ J                                                   # (n, 6, 12)
        WG = W[:, None] @ G                                         # (n, 3, 6, 6)
        GB = G @ B[:, None]                                         # (n, 3, 6, 12)
        GBt = np.swapaxes(GB, 2, 3)
        M = (np.swapaxes(B, 1, 2)[:, None] @ GB).sum(axis=0)        # (3, 12, 12) Uᵀ G_k U
        WGB = W[:, None] @ GB                                       # (n, 3, 6, 12)
        Q = (GBt[:, :, None] @ WGB[:, None]).sum(axis=0)            # (3, 3, 12, 12) Uᵀ G_k D G_l U
        PM = P @ M                                                  # (3, 12, 12)
        F = ((WG[:, :, None] * np.swapaxes(WG, 2, 3)[:, None]).sum(axis=(0, 3, 4))
             - 2.0 * (P * Q).sum(axis=(2, 3))                       # Q_lk = Q_klᵀ, P symmetric
             + (PM[:, None] * np.swapaxes(PM, 1, 2)[None]).sum(axis=(2, 3)))
        return W, B, M, Q, F

    def update(self, r: np.ndarray, J: np.ndarray, P: np.ndarray) -> np.ndarray:
        """One REML (Fisher-scoring) step of the variance components at residuals ``r``
        (Jacobian ``J``, covariance ``P`` of the fit): ``θ = F⁻¹ q`` with
        ``F_kl = tr(R G_k R G_l)``, ``q_k = rᵀ R G_k R r``, ``R = W − W J P Jᵀ W`` (the residual
        projector: the 12 fitted degrees of freedom taken out by leverage); a component that
        comes out below its floor is held there and the others re-solved. Returns the new
        residual covariances and whether the components settled."""
        G = self.G
        W, B, _, _, F = self._reml(J, P)
        u = (W @ r[..., None])[..., 0] - B @ (P @ (np.swapaxes(B, 1, 2) @ r[..., None]).sum(0))[..., 0]
        q = (u[:, None, None, :] @ G @ u[:, None, :, None])[..., 0, 0].sum(axis=0)
        free = np.ones(3, bool)
        theta = self.theta
        for _ in range(3):
            t = np.array(_FLOORS)
            try:
                t[free] = np.linalg.solve(F[np.ix_(free, free)],
                                          q[free] - F[np.ix_(free, ~free)] @ t[~free])
            except np.linalg.LinAlgError:
                t[:] = np.nan
            low = free & (t < _FLOORS)
            if not np.any(low):
                theta = t
                break
            free &= ~low
            theta = np.maximum(t, _FLOORS)
        # Far from the answer scoring can overshoot: when a component carrying a share of the
        # residuals more than triples or falls below a third (or a negligible one grows a
        # hundredfold), the multiplicative (EM) step θ_k q_k / (F θ)_k is taken instead, slower
        # but never leaving the positive cone. A negligible component may drop to its floor.
        share = self.theta * (F @ self.theta) / max(float(self.theta @ F @ self.theta), 1e-300)
        jump = np.where(share > 0.05, (theta > 3.0 * self.theta) | (theta < self.theta / 3.0),
                        theta > 100.0 * np.maximum(self.theta, 1e-4 * self.theta.max()))
        if not np.all(np.isfinite(theta)) or np.any(jump):
            theta = self.theta * q / np.maximum(F @ self.theta, 1e-300)
        theta = np.maximum(theta, _FLOORS)
        # Near the boundary scoring can cycle between two points: a component whose step
        # reverses its last one moves half as far.
        step = theta - self.theta
        if self.step is not None:
            step = np.where(step * self.step < 0.0, 0.5 * step, step)
            theta = np.maximum(self.theta + step, _FLOORS)
        self.step = step
        # Settled when the residual degrees of freedom the components account for,
        # θ_k tr(R G_k) = θ_k (F θ)_k (summing to 6n − 12), move by less than 1e-3 of them.
        Ft = F @ self.theta
        settled = (np.abs(theta - self.theta) @ Ft) <= 1e-3 * max(float(self.theta @ Ft), 1e-300)
        self.theta = theta
        return np.einsum("k,nkij->nij", self.theta, G), settled

    def covariances(self):
        """The estimated (camera, robot) pose noise, in the module's convention."""
        t = self.theta
        return np.diag([t[0]] * 3 + [t[1]] * 3), np.diag([t[2]] * 3 + [0.0] * 3)

    def kenward_roger(self, J: np.ndarray, P: np.ndarray) -> np.ndarray:
        """The covariance of ``(X, Z)`` to report when ``θ`` is estimated: ``P = H(θ̂)⁻¹`` with
        the uncertainty of ``θ̂`` propagated (Kenward & Roger 1997, Biometrics 53:983; the
        small-sample inference for fixed effects under REML variance components).

        ``H(θ̂)⁻¹`` is too small on average for two reasons, both of the order of
        ``Var(θ̂)/θ²`` — about 2/(residual degrees of freedom per component): 10 poses leave
        ``6n − 12 = 48`` shared by three components, some of them (the robot's rotation against
        the camera's, through the lever arm) poorly separated. (1) ``(X̂, Ẑ)`` varies more than
        ``H(θ)⁻¹`` says because ``θ̂`` varies, and ``H(θ̂)⁻¹`` is a biased estimate of ``H(θ)⁻¹``:
        to second order in ``θ̂ − θ`` both together are
        ``Φ_A = P + 2 P Λ P``, ``Λ = Σ_kl V_kl (Q_kl − M_k P M_l)``, ``V = Cov(θ̂) = 2 F⁻¹``
        (the inverse REML information; see :meth:`_reml` for ``M``, ``Q``, ``F``; the
        covariance is linear in ``θ``, so KR's second-derivative term is zero). (2) Even an
        unbiased ``Φ_A`` is a random matrix, and ``E[ξᵀ Φ_A⁻¹ ξ] > 6`` by Jensen: KR match
        the Wald statistic's first two moments to a scaled ``F(ℓ, m)``, whose mean gives
        ``E[ξᵀ Φ_A⁻¹ ξ] ≈ ℓ E*``, ``E* = 1 / (1 − A₂/ℓ)``,
        ``A₂ = Σ_kl V_kl tr(Θ P M_k P Θ P M_l P)``, ``Θ`` the inverse of the block's ``P``.
        Reporting ``E* Φ_A`` per block is then the covariance of the Student-t-like predictive
        distribution of the block (mean NEES ℓ). With one component this is exactly the
        t factor ``ν / (ν − 2)``, ``ν = 6n − 12``, and ``Φ_A = P``. X and Z get their own ``E*``
        (ℓ = 6 each); the joint covariance is ``D Φ_A D``, ``D = diag(√E*_X I₆, √E*_Z I₆)``.
        A component held at its floor keeps its uncertainty: an estimate of zero robot noise
        from 10 poses does not make the robot exact (taking it as known left the NEES of
        OpenCV's geometry at 10 poses 0.5 higher). ``1 − A₂/ℓ`` is kept
        above 0.05: so few residual degrees of freedom that it is not would be a t with about
        two, whose variance is unbounded."""
        _, _, M, Q, F = self._reml(J, P)
        try:
            V = 2.0 * np.linalg.inv(F)
        except np.linalg.LinAlgError:
            return P
        MP = M @ P                                                  # (3, 12, 12)
        MPM = MP[:, None] @ M[None]                                 # (3, 3, 12, 12)
        Lam = np.einsum("kl,klij->ij", V, Q - MPM)
        PA = P + 2.0 * P @ Lam @ P
        d = np.empty(12)
        for b in (slice(0, 6), slice(6, 12)):
            T = np.zeros((12, 12))
            T[b, b] = np.linalg.inv(P[b, b])
            Y = T @ P @ MP                                          # (3, 12, 12): Θ P M_k P
            A2 = float(np.einsum("kl,kij,lji->", V, Y, Y))
            d[b] = np.sqrt(1.0 / max(1.0 - A2 / 6.0, 0.05))
        PA = PA * d[:, None] * d[None, :]
        return 0.5 * (PA + PA.T)


def _linearise(A, C, AdCi, X, Z, noise: _Noise, use):
    E, r = _evaluate(A, C, X, Z)
    Jri = lie.se3_right_jacobian_inv(r)
    S = noise(X, C, r, Jri, use)
    J = np.empty((len(r), 6, 12))
    # r_i = Log(Z⁻¹ A_i X C_i): X Exp(δx) moves it by Jr⁻¹ Ad(C_i⁻¹) δx, Z Exp(δz) by
    # −Jl⁻¹(r) δz = −Jr⁻¹(r) Ad(E_i⁻¹) δz.
    J[:, :, :6] = Jri @ AdCi
    J[:, :, 6:] = -Jri @ lie.adjoint(dq.inv(E))
    return E, r, J, S


def _fit(A, C, X, Z, noise: _Noise, use) -> _Fit:
    """Gauss–Newton on ``(X, Z)`` over the samples ``use``, minimising Σ r_iᵀ Σ_r,i⁻¹ r_i; steps
    halved while the cost (at the step's weights) rises."""
    Au, Cu = A[use], C[use]
    AdCi = lie.adjoint(dq.inv(Cu))
    it = 0
    for it in range(1, _MAX_ITER + 1):
        E, r, J, S = _linearise(Au, Cu, AdCi, X, Z, noise, use)
        for _ in range(20 if noise.estimate else 1):
            W = np.linalg.inv(S)
            JtW = np.swapaxes(J, 1, 2) @ W
            H = (JtW @ J).sum(axis=0)
            g = np.einsum("nij,nj->i", JtW, r)
            if not noise.estimate:
                break
            # The shared noise settled at this linearisation's optimum (the residuals after
            # the step), so the outer iterations converge as fast as with known noise.
            try:
                Hi = np.linalg.inv(H)
            except np.linalg.LinAlgError:
                break
            S, settled = noise.update(r, J, Hi)
            if settled:
                break
        cost = float(np.einsum("ni,nij,nj->", r, W, r))
        try:
            step = -np.linalg.solve(H, g)
        except np.linalg.LinAlgError:
            step = None
        if step is None or not np.all(np.isfinite(step)):
            raise Infeasible("base_flange: the motions do not determine X and Z (singular "
                             "information); add poses rotating about other axes")
        t = 1.0
        for _ in range(30):
            Xn = dq.mul(X, lie.se3_exp(t * step[:6]))
            Zn = dq.mul(Z, lie.se3_exp(t * step[6:]))
            rn = _evaluate(Au, Cu, Xn, Zn)[1]
            if float(np.einsum("ni,nij,nj->", rn, W, rn)) <= cost * (1 + 1e-12) + 1e-300:
                break
            t *= 0.5
        X, Z = Xn, Zn
        if (t * t) * float(step @ H @ step) < _TOL or t < 1e-8:
            break
    E, r, J, S = _linearise(Au, Cu, AdCi, X, Z, noise, use)
    for _ in range(20 if noise.estimate else 1):   # the shared noise settled at the optimum
        JtW = np.swapaxes(J, 1, 2) @ np.linalg.inv(S)
        H = (JtW @ J).sum(axis=0)
        H = 0.5 * (H + H.T)
        if not noise.estimate:
            break
        S, settled = noise.update(r, J, np.linalg.inv(H))
        if settled:
            break
    try:
        P = np.linalg.inv(H)
    except np.linalg.LinAlgError:
        P = np.full((12, 12), np.inf)
    if not np.all(np.isfinite(P)):
        raise Infeasible("base_flange: the motions do not determine X and Z (singular "
                         "information); add poses rotating about other axes")
    P = 0.5 * (P + P.T)
    return _Fit(X, Z, E, r, J, np.array(S), H, P, it,
                noise.kenward_roger(J, P) if noise.estimate else P)


def _standardised(fit: _Fit) -> tuple[np.ndarray, np.ndarray]:
    """``r_iᵀ S_i⁻¹ r_i`` with ``S_i = Σ_r,i − J_i H⁻¹ J_iᵀ``, and ``S_i⁻¹ r_i`` (for the
    leave-one-out shift)."""
    Si = fit.S - fit.J @ fit.P @ np.swapaxes(fit.J, 1, 2)
    Si = 0.5 * (Si + np.swapaxes(Si, 1, 2))
    # A sample that alone fixes a direction has S_i singular there: pseudo-inverse, not NaN.
    y = np.einsum("nij,nj->ni", np.linalg.pinv(Si, rcond=1e-10, hermitian=True), fit.r)
    return np.einsum("ni,ni->n", fit.r, y), y


# ---- checks ------------------------------------------------------------------------------------
@dataclass
class _Prepared:
    setup: str
    F: np.ndarray
    A: np.ndarray
    C: np.ndarray
    use: np.ndarray          # samples not duplicates
    suspect: np.ndarray      # samples whose pairs are not screw-congruent
    warnings: list
    closed: tuple            # (X, Z, pairs) of the given reading
    readings: tuple
    condition: float
    excitation: float


def _reading(F, setup):
    return F if setup == "eye_in_hand" else dq.inv(F)


def _spread(A, C, X, Z, use):
    """Median rotation (rad) and position (m) of the per-sample ``A_i X C_i`` about ``Z``."""
    E = dq.mul(dq.mul(dq.mul(dq.inv(Z), A[use]), X), C[use])
    ang = 2.0 * np.arctan2(np.linalg.norm(E[:, 1:4], axis=1), np.abs(E[:, 0]))
    pos = np.linalg.norm(dq.to_pose(E)[1], axis=1)
    return float(np.median(ang)), float(np.median(pos))


def _rotation_information(A, i, j):
    """``Σ θ² (I − k kᵀ)`` over the pairs' robot rotation axes ``k``: the rotation of X is seen
    only across the axes; its condition number and the RMS angle of its smallest eigenvalue."""
    a = _hemisphere(dq.mul(dq.inv(A[j]), A[i]))
    v = a[:, 1:4]
    s = np.linalg.norm(v, axis=1)
    k = v / np.maximum(s, 1e-300)[:, None]
    th = 2.0 * np.arctan2(s, a[:, 0])
    M = np.einsum("p,pij->ij", th ** 2, np.eye(3) - k[:, :, None] * k[:, None, :])
    e = np.linalg.eigvalsh(M)
    m = max(len(th), 1)
    cond = float(e[-1] / e[0]) if e[0] > 1e-300 else float("inf")
    return cond, float(np.sqrt(max(e[0], 0.0) / m))


def _prepare(base_flange, camera_target, setup) -> _Prepared:
    setup = _setup(setup)
    F = _poses(base_flange, "base_flange")
    C = _poses(camera_target, "camera_target")
    n = F.shape[0]
    if C.shape[0] != n:
        raise FieldError(f"camera_target: {C.shape[0]} poses for {n} in base_flange "
                         f"(one per sample)")
    if n < _MIN_POSES:
        raise Infeasible(f"base_flange: {n} pose{'s' if n != 1 else ''}; at least {_MIN_POSES} "
                         f"are needed (two motions about different axes)")
    A = _reading(F, setup)
    warnings: list[str] = []

    cg = _congruence(A, C)
    i, j = cg.i, cg.j
    # Duplicates: the same sample twice (both sides unmoved); stale: the robot moved, the camera
    # did not (or the other way round).
    da = _pair_distance(A, i, j, left=True)
    db = _pair_distance(C, i, j, left=False)
    still_a = (cg.angle_a < _DUPLICATE_ANGLE) & (da < _DUPLICATE_DISTANCE)
    still_b = (cg.angle_b < _DUPLICATE_ANGLE) & (db < _DUPLICATE_DISTANCE)
    use = np.ones(n, bool)
    dup = still_a & still_b
    if np.any(dup):
        for p in np.flatnonzero(dup):
            use[j[p]] = False if use[i[p]] else use[j[p]]
        groups = sorted({(int(i[p]), int(j[p])) for p in np.flatnonzero(dup)})
        warnings.append(f"{_samples(sorted({k for g in groups for k in g}))}: duplicate poses "
                        f"({', '.join(f'{a} = {b}' for a, b in groups)}); each kept once")
    stale = still_a ^ still_b
    if np.any(stale):
        which = [(int(i[p]), int(j[p]), "robot" if still_a[p] else "camera")
                 for p in np.flatnonzero(stale)]
        warnings.append(f"{_samples(sorted({k for w in which for k in w[:2]}))}: stale poses ("
                        + "; ".join(f"{a} and {b}: the {who} did not move while the other did"
                                    for a, b, who in which[:5])
                        + ("; …" if len(which) > 5 else "") + ")")
    if np.count_nonzero(use) < _MIN_POSES:
        raise Infeasible(f"base_flange: {np.count_nonzero(use)} distinct poses after removing "
                         f"duplicates; at least {_MIN_POSES} are needed")
    pu = use[i] & use[j]
    largest = float(np.max(cg.angle_a[pu]))
    if largest < _PURE_TRANSLATION:
        raise Infeasible(f"base_flange: pure translation: no two samples differ in rotation by "
                         f"more than {np.degrees(largest):.2f}°; the camera's position cannot be "
                         f"found without rotations about at least two axes "
                         f"({_samples(np.flatnonzero(use))})")
    cond, excitation = _rotation_information(A, i[pu], j[pu])
    if excitation < _MIN_EXCITATION:
        raise Infeasible(f"base_flange: the rotation axes of all motions are parallel "
                         f"(smallest rotation excitation {np.degrees(excitation):.2f}°, "
                         f"condition number {cond:.3g} of the rotation information); rotate "
                         f"about at least two different axes ({_samples(np.flatnonzero(use))})")
    if largest < _SMALL_ROTATION:
        warnings.append(f"{_samples(np.flatnonzero(use))}: small rotations (largest between "
                        f"two samples {np.degrees(largest):.1f}°); X is poorly determined")
    if excitation < _LOW_EXCITATION:
        warnings.append(f"{_samples(np.flatnonzero(use))}: rotation axes nearly parallel or "
                        f"coplanar (smallest excitation {np.degrees(excitation):.2f}°, condition "
                        f"number {cond:.3g} of the rotation information)")

    # Screw congruence: angle and pitch of A-motions and C-motions must agree.
    dth = np.abs(cg.angle_a - cg.angle_b)[pu]
    dd = np.abs(cg.pitch_a - cg.pitch_b)[pu]
    ip, jp = i[pu], j[pu]
    med_th, med_d = float(np.median(dth)), float(np.median(dd))
    if med_th > _MISMATCH_ANGLE:
        raise Infeasible(f"base_flange, camera_target: the robot and camera motions do not "
                         f"correspond: their rotation angles differ by {np.degrees(med_th):.1f}° "
                         f"(median over pairs; about the noise when they do); samples misaligned "
                         f"in time or paired wrongly ({_samples(np.flatnonzero(use))})")
    _units(cg, pu, use)
    # A pitch is the translation along an axis that rotation noise tilts by about σ/θ, so it is
    # noisy by |t| σ/θ: centimetres on healthy data with the target metres away (OpenCV's
    # geometry at 0.5°: 45 mm median). Pitches off by more than that only warn: misaligned
    # samples show in the angles, and a wrong reading is refused below.
    s_rot = max(1.4826 * med_th, np.radians(0.01))
    expected = s_rot * (da + db)[pu] / np.maximum(cg.angle_a[pu], 0.1) + 1e-3
    if med_d > _MISMATCH_PITCH and float(np.median(dd / expected)) > 5.0:
        warnings.append(f"{_samples(np.flatnonzero(use))}: the robot's and the camera's "
                        f"translations along the screw axes differ by {1e3 * med_d:.1f} mm "
                        f"(median over pairs) while the angles agree "
                        f"({np.degrees(med_th):.2f}°): samples misaligned in time, or noisy "
                        f"camera poses far from the target")
    s_th = max(1.4826 * med_th, np.radians(0.01))
    s_d = max(1.4826 * med_d, 1e-4)
    score = np.maximum(_per_sample_median(n, ip, jp, dth / s_th),
                       _per_sample_median(n, ip, jp, dd / s_d))
    suspect = use & (score > _SUSPECT)
    if np.count_nonzero(use & ~suspect) < _MIN_POSES:
        suspect[:] = False

    # The readings: the given one against the swapped setup and inverted camera poses. Both
    # swapped is no alternative: F⁻¹ Z C⁻¹ = X is the same equation with X and Z exchanged.
    base_use = use & ~suspect
    closed = _closed_form(A, C, base_use)
    if closed is None:
        raise Infeasible(f"base_flange: fewer than two pairs of samples rotate by more than "
                         f"{np.degrees(_MIN_PAIR_ANGLE):.0f}°; add poses rotating about "
                         f"different axes")
    readings = []
    other = "eye_to_hand" if setup == "eye_in_hand" else "eye_in_hand"
    for name, Ar, Cr in ((setup, A, C),
                         (other, _reading(F, other), C),
                         (f"{setup}, camera_target inverted", A, dq.inv(C))):
        res = closed if Ar is A and Cr is C else _closed_form(Ar, Cr, base_use)
        if res is None:
            continue
        readings.append((name,) + _spread(Ar, Cr, res[0], res[1], base_use))
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
    return _Prepared(setup, F, A, C, use, suspect, warnings, closed, tuple(readings), cond,
                     excitation)


def _pair_distance(P, i, j, left: bool) -> np.ndarray:
    M = dq.mul(dq.inv(P[j]), P[i]) if left else dq.mul(P[j], dq.inv(P[i]))
    return np.linalg.norm(dq.to_pose(M)[1], axis=1)


def _units(cg: _Congruence, pu: np.ndarray, use: np.ndarray) -> None:
    """Pitch of the robot's motions against the camera's: a ratio near 1000 is millimetres."""
    da, db = cg.pitch_a[pu], cg.pitch_b[pu]
    if np.sum(db * db) <= 0.0 or np.sum(da * da) <= 0.0:
        return
    s = float(np.sum(da * db) / np.sum(db * db))     # da ≈ s db
    resid = np.sqrt(np.mean((da - s * db) ** 2))
    if resid > 0.3 * np.sqrt(np.mean(da * da)):
        return                                         # no clean scale: not a unit problem
    if s < 0.1 or s > 10.0:
        big, small, f = (("camera_target", "base_flange", 1 / s) if s < 1 else
                         ("base_flange", "camera_target", s))
        unit = " (millimetres given as metres?)" if 300 < f < 3000 else ""
        raise Infeasible(f"{big}: translations {f:.4g}× those of {small} along the same screw "
                         f"axes{unit}; give both in metres ({_samples(np.flatnonzero(use))})")


# ---- corner level ------------------------------------------------------------------------------
_MIN_CORNERS = 4


@dataclass
class _Views:
    points: np.ndarray      # (N, 3) board points, all views stacked
    pixels: np.ndarray      # (N, 2) their detections
    view: np.ndarray        # (N,) the sample each belongs to
    K: np.ndarray           # (n, 3, 3)


def _views(corners, n: int) -> _Views:
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
    return dq.to_matrix(dq.mul(dq.mul(dq.inv(X), dq.inv(_reading(Fi, setup))), Z))


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


def _corner_fit(F, setup, X, Z, views: _Views, inlier, robot, refine_focal: bool,
                pixel_sigma: Optional[float], refine_board: bool = False) -> _CornerFit:
    """Maximum likelihood on the corners: pixels with isotropic noise σ (given, or estimated
    per view from its reprojection errors, the fit's leverage in that view taken out: a view's
    blur, distance and obliquity set it), unknowns ``X``, ``Z`` (right perturbations), a
    focal-length scale when ``refine_focal``, and a correction ``δ_i`` of each
    robot pose ``F_i Exp(δ_i)`` under the robot noise ``robot``: given ((n, 6, 6)), estimated
    (``"estimate"``: isotropic rotation and translation variances, MacKay's evidence fixed
    point on the corrections), or None (robot poses exact). Gauss–Newton from the pose-level answer.
    ``refine_board`` frees a scale of the board's points too (after the pose level found the
    camera's translations at another scale: its uncertainty then enters the covariance)."""
    idx = np.flatnonzero(inlier)
    n_in = len(idx)
    sel = np.isin(views.view, idx)
    sub = _Views(views.points[sel], views.pixels[sel],
                 np.searchsorted(idx, views.view[sel]), views.K[idx])
    Fu = F[idx]
    # δ of F moves A by δ (eye_in_hand) or −Ad(F) δ (eye_to_hand: A = F⁻¹).
    toA = None if setup == "eye_in_hand" else -lie.adjoint(Fu)
    estimate = isinstance(robot, str)
    use_robot = robot is not None
    nf = 1 if refine_focal else 0
    nb = 1 if refine_board else 0
    off = 12 + nf + nb
    npar = off + (6 * n_in if use_robot else 0)
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

    def prior_rows():
        S = (np.broadcast_to(np.diag(theta), (n_in, 6, 6)) if estimate else
             np.asarray(robot)[idx])
        e, Q = np.linalg.eigh(S)
        e = np.maximum(e, 1e-12 * e.max(axis=1, keepdims=True) + 1e-30)
        return np.swapaxes(Q / np.sqrt(e)[:, None, :], 1, 2)     # Σ^-1/2 per view

    H = None
    settled = not estimate
    for em in range(_EM_ROUNDS + 1 if estimate else 1):
        settled = settled or em == _EM_ROUNDS
        prior = prior_rows() if use_robot else None
        cost = np.inf
        # While the robot's variances are still moving a couple of steps per round do; the
        # round after they settle converges.
        for it in range(50 if settled else 2):
            M = _corner_cameras(Fu, setup, X, Z, delta)
            pts = sub.points * board
            pc, u, Jp, ds = _project(M, _Views(pts, sub.pixels, sub.view, sub.K), scale)
            behind = pc[:, 2] <= 0.0
            if np.any(behind):
                k = int(idx[sub.view[np.flatnonzero(behind)[0]]])
                raise Infeasible(f"corners[{k}]: the board lies behind the camera in the "
                                 f"solution; do the corners belong to the poses (same order, "
                                 f"same board frame)?")
            e = (u - sub.pixels).reshape(-1)
            if pixel_sigma is None:
                e2 = np.bincount(sub.view, (e.reshape(N, 2) ** 2).sum(axis=1), minlength=n_in)
                dof = np.maximum(2 * corners_in - leverage, 1.0)
                sigma = np.sqrt(np.maximum(e2 / dof, 1e-18))
            s_row = np.repeat(sigma[sub.view], 2)
            R = M[sub.view, :3, :3]
            dX = np.zeros((N, 3, 6))
            dX[:, :, :3] = lie.so3_hat(pc)
            dX[:, :, 3:] = -np.eye(3)
            dZ = np.concatenate([-R @ lie.so3_hat(pts), R], axis=2)
            # The global columns (X, Z, the focal and board scales) of every pixel row...
            Jg = np.empty((2 * N, off))
            Jg[:, :6] = (Jp @ dX).reshape(2 * N, 6) / s_row[:, None]
            Jg[:, 6:12] = (Jp @ dZ).reshape(2 * N, 6) / s_row[:, None]
            if nf:
                Jg[:, 12] = ds.reshape(-1) / s_row
            if nb:       # the board's points scaled by (1 + ε): the camera's points by R p ε
                Jg[:, 12 + nf] = (Jp @ (R @ pts[..., None]))[..., 0].reshape(-1) / s_row
            r = e / s_row
            Jd = None
            if use_robot:
                # ... and its view's robot correction: A ← A Exp(δ_A) moves C by
                # Exp(−Ad(X⁻¹) δ_A) on the left, the X column's derivative times Ad(X⁻¹).
                dA = dX @ lie.adjoint(dq.inv(X))
                if toA is not None:
                    dA = dA @ toA[sub.view]
                Jd = ((Jp @ dA) / sigma[sub.view, None, None]).reshape(2 * N, 6)
            step, H, lev = _arrow_step(Jg, Jd, r, prior, delta, starts)
            X = dq.mul(X, lie.se3_exp(step[:6]))
            Z = dq.mul(Z, lie.se3_exp(step[6:12]))
            if nf:
                scale *= 1.0 + step[12]
            if nb:
                board *= 1.0 + step[12 + nf]
            if use_robot:
                delta = delta + step[off:].reshape(n_in, 6)
            # the pixel dof the fit takes, per view (REML: each σ from what the fit leaves)
            leverage = np.add.reduceat(lev.reshape(N, 2).sum(axis=1), starts)
            new = H.cost
            if H.moved(step) < _TOL and abs(cost - new) <= 1e-9 * new:
                break
            cost = new
        if settled:
            break
        # MacKay's fixed point (the evidence's stationary point): θ = Σ δ̂² / γ with
        # γ = Σ (1 − P_kk / θ) the number of correction components the corners determine;
        # unlike EM it drops to ~0 in a step when the robot is exact.
        d2 = (delta ** 2).sum(axis=0)
        gam = (1.0 - np.diagonal(H.Pdd, axis1=1, axis2=2) / theta).sum(axis=0)
        gam = np.repeat([gam[:3].sum(), gam[3:].sum()], 3)
        num = np.repeat([d2[:3].sum(), d2[3:].sum()], 3)
        new_theta = np.maximum(num / np.maximum(gam, 1e-3), _ROBOT_FLOOR)
        settled = bool(np.all(np.abs(new_theta - theta) <= 0.1 * theta + _ROBOT_FLOOR))
        theta = new_theta
    P = H.Pgg
    full = None
    if use_robot:
        full = np.zeros((len(F), 6))
        full[idx] = delta
    M = _corner_cameras(F, setup, X, Z, full)
    _, u, _, _ = _project(M, _Views(views.points * board, views.pixels, views.view, views.K),
                          scale)
    err = np.sum((u - views.pixels) ** 2, axis=1)
    count = np.bincount(views.view, minlength=len(F))
    rms = np.sqrt(np.bincount(views.view, err, minlength=len(F)) / np.maximum(count, 1))
    P12 = 0.5 * (P[:12, :12] + P[:12, :12].T)
    dof = np.maximum(2 * corners_in - leverage, 1.0)
    pooled = float(pixel_sigma or np.sqrt(np.sum(sigma ** 2 * dof) / np.sum(dof)))
    return _CornerFit(X, Z, P12, rms, scale, pooled, float(np.sqrt(P[12, 12])) if nf else 0.0,
                      np.diag(theta) if estimate else None, board,
                      float(np.sqrt(P[12 + nf, 12 + nf])) if nb else 0.0)


# ---- the API -----------------------------------------------------------------------------------
def check(base_flange, camera_target, setup: str = "eye_in_hand") -> tuple[str, ...]:
    """The data checks of :func:`calibrate` without the refinement: raises what it would raise
    (``FieldError`` for malformed input, ``Infeasible`` for unusable data), returns its warnings
    (each naming the samples), samples failing screw congruence among them."""
    p = _prepare(base_flange, camera_target, setup)
    w = list(p.warnings)
    if np.any(p.suspect):
        w.append(f"{_samples(np.flatnonzero(p.suspect))}: robot and camera motions not "
                 f"screw-congruent with the other samples (outliers, a robot that had not "
                 f"settled, or a marker flip)")
    return tuple(w)


def calibrate(base_flange, camera_target, setup: str = "eye_in_hand", *, robust: bool = True,
              corners=None, camera_covariance=None, robot_covariance=None,
              refine_focal: bool = False, pixel_sigma: Optional[float] = None) -> Calibration:
    """Solve ``A_i X C_i = Z`` (see the module docstring) for ``x`` and ``z`` with covariances.

    ``camera_covariance`` / ``robot_covariance``: noise of ``camera_target`` / ``base_flange``
    ((6, 6) or (n, 6, 6), right perturbation, rotation first); with neither given the noise is
    estimated from the residuals; with only the camera's given the robot poses are taken as exact.
    ``robust`` rejects samples failing the χ² gate (named in ``rejected``); otherwise they are
    kept and named in a warning.

    ``corners`` (one ``(board_points (k,3), image_points (k,2), K)`` per sample, undistorted
    pixels, board points in the target frame) adds a corner-level refinement after the pose-level
    one (:func:`_corner_fit`): ``x``, ``z`` and their covariances then come from the corners,
    ``reprojection`` holds each view's RMS error (px); ``refine_focal`` estimates one scale of
    the focal lengths too (``focal_scale``); ``pixel_sigma`` (px) is the corner noise, estimated
    per view from the reprojection errors when not given (the reported one their pooled RMS).
    The robot's noise there is ``robot_covariance`` when given, estimated when neither
    covariance is given, and none (exact robot poses) when only ``camera_covariance`` is.

    Two readings of the data fit as well as the one given, and are caught by plausibility
    instead (:func:`_plausible`, :func:`_camera_scale`): both poses inverted (``T_flange_base``
    and ``T_target_camera``: X and Z exchange roles exactly) and the camera's translations at
    another scale (a wrong board size). Where the data say which reading is right, the answer is
    that reading's, with a warning saying what was corrected; where they cannot, ``Infeasible``.
    """
    return _calibrate(base_flange, camera_target, setup, robust, corners, camera_covariance,
                      robot_covariance, refine_focal, pixel_sigma)


def _calibrate(base_flange, camera_target, setup, robust, corners, camera_covariance,
               robot_covariance, refine_focal, pixel_sigma, inverted: bool = False,
               rescaled: Optional[tuple[float, float]] = None) -> Calibration:
    """:func:`calibrate`. ``inverted``: this is the re-solve on both poses inverted (not to be
    turned back); ``rescaled``: ``(λ, σ)`` when it is the re-solve on camera translations
    scaled by ``λ`` (whose uncertainty then enters the covariance)."""
    p = _prepare(base_flange, camera_target, setup)
    n = p.F.shape[0]
    views = None if corners is None else _views(corners, n)
    if pixel_sigma is not None and not (np.isfinite(pixel_sigma) and pixel_sigma > 0):
        raise FieldError(f"pixel_sigma: must be a positive number of pixels, got {pixel_sigma!r}")
    SC = _noise(camera_covariance, "camera_covariance", n)
    SRob = _noise(robot_covariance, "robot_covariance", n)
    if SC is None and SRob is not None:
        raise FieldError("camera_covariance: needed when robot_covariance is given (or give "
                         "neither to estimate the noise)")
    estimate = SC is None
    # Noise of A_i = base_flange_i⁻¹ (eye_to_hand) is the inverse's: Ad(F) Σ Ad(F)ᵀ.
    SA = None
    if SRob is not None:
        SA = SRob if p.setup == "eye_in_hand" else lie.cov_inverse(p.F, SRob)
        if not np.any(SA):
            SA = None
    noise = _Noise(SA, SC, estimate,
                   lie.adjoint(p.F) if p.setup == "eye_to_hand" and estimate else None)
    if not estimate:
        S0 = noise(p.closed[0], p.C, np.zeros((n, 6)), np.broadcast_to(np.eye(6), (n, 6, 6)),
                   np.ones(n, bool))
        singular = np.flatnonzero(~(np.linalg.eigvalsh(S0)[:, 0] > 0.0))
        if len(singular):
            i = int(singular[0])
            given = f"camera_covariance[{i}]" + (
                f", robot_covariance[{i}]" if SRob is not None else "")
            raise FieldError(f"{given}: the residual covariance of this sample (its camera and "
                             f"robot noise together) is singular; give every pose some noise "
                             f"in every axis")
    warnings = list(p.warnings)
    X0, Z0 = p.closed[0], p.closed[1]

    inlier = p.use & ~p.suspect
    fit = _fit(p.A, p.C, X0, Z0, noise, inlier)
    # The gate runs in both modes; without ``robust`` its outliers are named, not left out.
    for _ in range(5):
        r_all, S_all, nis_all = _against(p, fit, noise, inlier)
        new = p.use & (nis_all <= _GATE_6)
        if np.count_nonzero(new) < _MIN_POSES or np.array_equal(new, inlier):
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

    r_all, S_all, nis = _against(p, fit, noise, inlier)
    idx = np.flatnonzero(inlier)
    nis_in, y = _standardised(fit)
    # Leaving sample i out moves (X, Z) by H⁻¹ J_iᵀ S_i⁻¹ r_i (Sherman–Morrison, first order).
    loo = np.zeros((n, 2))
    shift = np.einsum("ij,nkj,nk->ni", fit.P, fit.J, y)
    m = lie.se3_exp(shift[:, :6])
    loo[idx, 0] = 2.0 * np.arctan2(np.linalg.norm(m[:, 1:4], axis=1), np.abs(m[:, 0]))
    loo[idx, 1] = np.linalg.norm(dq.to_pose(m)[1], axis=1)
    E_all = dq.mul(dq.mul(dq.mul(dq.inv(fit.Z), p.A), fit.X), p.C)
    residuals = np.column_stack([np.linalg.norm(r_all[:, :3], axis=1),
                                 np.linalg.norm(dq.to_pose(E_all)[1], axis=1)])
    xi = lie.se3_log(dq.mul(dq.inv(fit.X), X0))
    agree = (float(np.linalg.norm(xi[:3])),
             float(np.linalg.norm(dq.to_pose(X0)[1] - dq.to_pose(fit.X)[1])),
             float(xi @ np.linalg.solve(fit.reported[:6, :6], xi)))
    # The closed form weighs nothing and is far less precise than the refinement (on OpenCV's
    # geometry 10–20 mm off at 0.1° / 0.5 mm noise): only a gross disagreement is a sign.
    if agree[2] > 1e4 and (agree[0] > np.radians(3.0) or agree[1] > 0.05):
        warnings.append(f"{_samples(idx)}: the closed form and the refined X differ by "
                        f"{np.degrees(agree[0]):.2f}° / {1e3 * agree[1]:.1f} mm "
                        f"(NEES {agree[2]:.3g}): the model may not fit the data")
    # Robot and camera poses both inverted fit exactly as well as the truth (F⁻¹ Z C⁻¹ = X: X
    # and Z exchange roles), so the residuals cannot tell; plausibility can.
    given, other = _plausible(p, fit.X, fit.Z, inlier), _plausible(p, fit.Z, fit.X, inlier, True)
    if not given.mount_ok and not inverted and rescaled is None:
        if other.mount_ok and other.front and given.behind:
            cal = _calibrate(dq.inv(p.F), dq.inv(p.C), p.setup, robust, corners,
                             _inverse_noise(p.C, SC), _inverse_noise(p.F, SRob), refine_focal,
                             pixel_sigma, inverted=True)
            return _warned(cal, f"{_samples(idx)}: base_flange and camera_target look both "
                                f"inverted (T_flange_base, T_target_camera): as given "
                                f"{given.says}, and the target lies behind the camera in every "
                                f"sample; inverted, {other.says} with the target in front. "
                                f"Solved as inverted; fix the conventions (the flange in the "
                                f"robot's base frame, the target in the camera's)")
        if other.mount_ok and not (given.front and other.behind):
            raise Infeasible(f"base_flange, camera_target: as given {given.says}; with both "
                             f"inverted (T_flange_base, T_target_camera: an exact fit too) "
                             f"{other.says}. The data cannot tell which; check both pose "
                             f"conventions (the flange in the robot's base frame, the target "
                             f"in the camera's) ({_samples(idx)})")
    if not given.mount_ok:
        why = (f"though the target lies in front of the camera as given and behind it "
               f"inverted" if given.front and other.behind else
               f"and as inverted poses {other.says}")
        warnings.append(f"{_samples(idx)}: {given.says}, {why}: check the mount and the pose "
                        f"conventions (both poses inverted fit as well)")
    scale = _camera_scale(fit, p.C[inlier])
    P_scale = 0.0
    if rescaled is not None:
        # The re-solve on scaled translations: λ's uncertainty widens the covariance.
        P_scale = scale[2]
        scale = (rescaled[0] * scale[0], rescaled[0] * scale[1], None)
    elif abs(scale[0] - 1.0) > max(_SCALE_SIGMAS * scale[1], _MIN_SCALE):
        lam = scale[0]
        Cs = p.C.copy()
        Cs[:, 4:] *= lam            # the dual part carries the translation linearly
        D = np.diag([1.0] * 3 + [lam] * 3)
        cs = None if views is None else [
            (views.points[views.view == k] * lam, views.pixels[views.view == k], views.K[k])
            for k in range(n)]
        cal = _calibrate(p.F, Cs, p.setup, robust, cs, None if SC is None else D @ SC @ D,
                         SRob, refine_focal, pixel_sigma, inverted, scale[:2])
        return _warned(cal, f"{_samples(idx)}: the camera's translations fit best scaled by "
                            f"{lam:.4f} ± {scale[1]:.4f} against the robot's: a wrong board "
                            f"size, or a camera scale error? Solved with camera_target's "
                            f"translations (and the board's points) scaled by {lam:.4f}, its "
                            f"uncertainty in the covariance; X's translation was off by "
                            f"{1e3 * _moved(fit.X, cal.x):.2f} mm without")
    X, Z, P = fit.X, fit.Z, fit.reported + P_scale
    Hx = np.linalg.inv(P)
    corner = {}
    if views is not None:
        robot = "estimate" if estimate else SRob
        cf = _corner_fit(p.F, p.setup, X, Z, views, inlier, robot, refine_focal, pixel_sigma,
                         refine_board=rescaled is not None)
        if rescaled is not None:
            scale = (rescaled[0] * cf.board_scale, rescaled[0] * cf.board_sigma, None)
        X, Z, P, Hx = cf.X, cf.Z, cf.P, np.linalg.inv(cf.P)
        corner = dict(reprojection=cf.reprojection, focal_scale=cf.focal_scale,
                      focal_sigma=cf.focal_sigma, pixel_sigma=cf.pixel_sigma)
        if cf.robot_covariance is not None:
            corner["robot_covariance"] = cf.robot_covariance
        bad = np.flatnonzero(inlier & (cf.reprojection > 5.0 * cf.pixel_sigma + 0.5))
        if len(bad):
            warnings.append(f"{_samples(bad)}: reprojection errors of " + ", ".join(
                f"{cf.reprojection[k]:.2f}" for k in bad) + f" px, against {cf.pixel_sigma:.2f} "
                f"px overall: corners misdetected, or the robot pose off?")
    return Calibration(
        setup=p.setup, x=X, z=Z, covariance_x=P[:6, :6].copy(),
        covariance_z=P[6:, 6:].copy(), residuals=residuals, warnings=tuple(warnings),
        inliers=inlier, rejected=tuple(rejected), covariance=P, information=Hx,
        noise_model="estimated" if estimate else "given",
        camera_covariance=noise.covariances()[0] if estimate else SC,
        **({"robot_covariance": noise.covariances()[1] if estimate else SRob} | corner),
        residual_covariance=np.array(S_all), nis=nis, leave_one_out=loo, closed_form_x=X0,
        closed_form_z=Z0, agreement=agree, rotation_condition=p.condition,
        excitation=p.excitation, iterations=fit.iterations, readings=p.readings,
        camera_scale=scale[:2])


@dataclass(frozen=True)
class _Reading:
    mount_ok: bool    # the flange-mounted part near the flange, the fixed one off the base
    front: bool       # the target in front of the camera (z > 0 in T_camera_target), every sample
    behind: bool      # ... behind it in every sample
    says: str


def _plausible(p: _Prepared, X, Z, inlier, inverted: bool = False) -> _Reading:
    """How plausible the answer ``(X, Z)`` is as a mount (``inverted``: the reading of both poses
    inverted, where ``(Z, X)`` of the given fit is the answer and ``C⁻¹`` the camera poses)."""
    mount, fixed = (X, Z) if p.setup == "eye_in_hand" else (Z, X)
    reach = float(np.linalg.norm(dq.to_pose(mount)[1]))
    base = float(np.linalg.norm(dq.to_pose(fixed)[1]))
    C = p.C[inlier]
    depth = dq.to_pose(dq.inv(C) if inverted else C)[1][:, 2]
    what = ("camera", "target") if p.setup == "eye_in_hand" else ("target", "camera")
    return _Reading(reach <= _MAX_MOUNT and base >= _MIN_FIXED, bool(np.all(depth > 0.0)),
                    bool(np.all(depth < 0.0)),
                    f"the {what[0]} comes out {reach:.2f} m from the flange and the {what[1]} "
                    f"{base:.2f} m from the robot base")


def _inverse_noise(T, S):
    return None if S is None else lie.cov_inverse(T, S)


def _moved(a, b) -> float:
    return float(np.linalg.norm(dq.to_pose(a)[1] - dq.to_pose(b)[1]))


def _warned(cal: Calibration, warning: str) -> Calibration:
    return replace(cal, warnings=(warning,) + cal.warnings)


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
    sigma = float(np.sqrt(max(Hi[12, 12], 0.0)))
    if not np.isfinite(sigma):
        return 1.0 + float(step[12]), float("inf"), np.zeros((12, 12))
    # λ free widens (X, Z)'s covariance from H₁₂⁻¹ to (H⁻¹)₁₂: by h hᵀ / (H⁻¹)_λλ, h = (H⁻¹)_:12,λ.
    h = Hi[:12, 12]
    extra = np.outer(h, h) / Hi[12, 12] if Hi[12, 12] > 0.0 else np.zeros((12, 12))
    return 1.0 + float(step[12]), sigma, extra


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


def view_at(base_flange, x, z, setup: str = "eye_in_hand") -> np.ndarray:
    """The ``T_camera_target`` a calibration ``(x, z)`` predicts at the robot poses
    ``base_flange``: eye-in-hand ``x⁻¹ · base_flange⁻¹ · z``, eye-to-hand
    ``x⁻¹ · base_flange · z``."""
    if _setup(setup) == "eye_in_hand":
        return dq.mul(dq.mul(dq.inv(x), dq.inv(base_flange)), z)
    return dq.mul(dq.mul(dq.inv(x), base_flange), z)


def flange_for(camera_target, x, z, setup: str = "eye_in_hand") -> np.ndarray:
    """The ``T_base_flange`` at which a calibration ``(x, z)`` has the camera see the target at
    ``camera_target`` (the inverse of :func:`view_at`)."""
    if _setup(setup) == "eye_in_hand":
        return dq.mul(dq.mul(z, dq.inv(camera_target)), dq.inv(x))
    return dq.mul(dq.mul(x, camera_target), dq.inv(z))


def next_best_pose(calibration: Calibration, base_flange, camera_target, candidates) -> np.ndarray:
    """Indices of the candidate robot poses ``T_base_flange`` (m, 8), most informative first:
    the one whose sample, added to the information of ``calibration``, shrinks the covariance of
    X most (smallest determinant of X's marginal). The candidate's camera pose is predicted from
    the calibration; its noise is the calibration's noise model (``base_flange`` and
    ``camera_target`` are the samples it was solved from, checked for shape only)."""
    _poses(base_flange, "base_flange")
    _poses(camera_target, "camera_target")
    cand = _poses(candidates, "candidates")
    if cand.shape[0] == 0:
        raise FieldError("candidates: no candidate poses")
    c = calibration
    A = _reading(cand, c.setup)
    X, Z = c.x, c.z
    C = dq.mul(dq.mul(dq.inv(X), dq.inv(A)), Z)             # A X C = Z
    m = cand.shape[0]
    I6 = np.broadcast_to(np.eye(6), (m, 6, 6))
    J = np.concatenate([lie.adjoint(dq.inv(C)), -I6], axis=2)   # at r = 0
    # The candidate's noise: the calibration's noise model (given or estimated), that of its
    # last sample when given per sample.
    SC = np.broadcast_to(np.asarray(c.camera_covariance).reshape(-1, 6, 6)[-1], (m, 6, 6))
    SA = None
    if c.robot_covariance is not None:
        SA = np.broadcast_to(np.asarray(c.robot_covariance).reshape(-1, 6, 6)[-1], (m, 6, 6))
        if c.setup == "eye_to_hand":
            SA = lie.cov_inverse(cand, SA)
    S = _transported(X, C, SA, SC, I6)
    W = np.linalg.inv(S)
    H = c.information[None] + np.swapaxes(J, 1, 2) @ W @ J
    P = np.linalg.inv(H)
    score = np.linalg.slogdet(P[:, :6, :6])[1]
    return np.argsort(score, kind="stable")
