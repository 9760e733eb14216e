"""Shared by the dual-quaternion tests: tolerances relative to the translation scale, pose and
matrix comparisons up to sign, poses at given rotation angles, and DLB by its definition."""
from __future__ import annotations

import numpy as np

from dqpose import dq
from tests import reference as ref
from tests.conftest import random_dqs

TOL = 1e-12
N = 5000
PI = np.pi


# Rotation angles where the closed forms change branch or degenerate.
HARD_ANGLES = [0.0, 1e-300, 1e-160, 1e-15, 1e-12, 1e-9, 1e-6, PI - 1e-6, PI - 1e-9,
               PI - 1e-12, PI - 4e-16, PI]


def tscale(*Ts: np.ndarray) -> np.ndarray:
    """max(1, |t|) over the given poses (matrices), the scale of the absolute tolerance."""
    s = np.ones(np.broadcast_shapes(*(T.shape[:-2] for T in Ts)))
    for T in Ts:
        s = np.maximum(s, np.linalg.norm(T[..., :3, 3], axis=-1))
    return s


def matrix_error(A: np.ndarray, B: np.ndarray, scale: np.ndarray) -> float:
    return float(np.max(np.abs(A - B).max(axis=(-2, -1)) / scale, initial=0.0))


def assert_matrices_close(A, B, scale=None, tol=TOL):
    scale = tscale(B) if scale is None else scale
    err = matrix_error(A, B, scale)
    assert err <= tol, f"max scaled error {err:.3g} > {tol:g}"


def assert_poses_close(q, T, scale=None, tol=TOL):
    """Dual quaternions ``q`` (any sign) represent the matrices ``T``."""
    assert_matrices_close(ref.matrix_from_dq(q), T, scale, tol)


def align(q: np.ndarray, p: np.ndarray) -> np.ndarray:
    """q with each element's sign chosen to match p's real part (q ~ -q)."""
    s = np.where(np.sum(q[..., :4] * p[..., :4], axis=-1) < 0.0, -1.0, 1.0)
    return q * s[..., None]


def dq_error(q: np.ndarray, p: np.ndarray) -> float:
    """Largest difference up to sign, relative to max(1, |t|) of p."""
    scale = np.maximum(1.0, np.linalg.norm(ref.translation_of_dq(p), axis=-1))
    return float(np.max(np.abs(align(q, p) - p).max(axis=-1) / scale, initial=0.0))


def assert_dq_close(q, p, tol=TOL):
    err = dq_error(q, p)
    assert err <= tol, f"max scaled error {err:.3g} > {tol:g}"


def random_signs(rng, shape) -> np.ndarray:
    return np.where(rng.random(shape) < 0.5, -1.0, 1.0)[..., None]


def unit_axes(rng, n) -> np.ndarray:
    a = rng.normal(size=(n, 3))
    return a / np.linalg.norm(a, axis=-1, keepdims=True)


def quats_at_angle(rng, theta: float, n: int) -> np.ndarray:
    """Unit quaternions rotating by exactly ``theta`` about random axes, random signs."""
    w = 0.0 if theta == PI else np.cos(0.5 * theta)  # cos(pi/2) is 6e-17, not 0
    r = np.concatenate([np.full((n, 1), w), unit_axes(rng, n) * np.sin(0.5 * theta)], axis=-1)
    return r * random_signs(rng, n)


def twists_near(rng, n, max_angle, scale=1.0) -> np.ndarray:
    """Twists with rotation angle uniform in [0, max_angle] and translation ~ N(0, scale^2)."""
    om = unit_axes(rng, n) * rng.uniform(0.0, max_angle, size=(n, 1))
    return np.concatenate([om, scale * rng.normal(size=(n, 3))], axis=-1)


def dlb_definition(Q: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Sum w_i q_i / |.| with every q_i in the hemisphere of the largest weight's pose."""
    w = np.broadcast_to(w / w.sum(axis=-1, keepdims=True), Q.shape[:-1])
    k = np.argmax(w, axis=-1)
    pivot = np.take_along_axis(Q, k[..., None, None], axis=-2)
    sign = np.where(np.sum(Q[..., :4] * pivot[..., :4], axis=-1) < 0.0, -1.0, 1.0)
    s = np.sum((w * sign)[..., None] * Q, axis=-2)
    r, d = s[..., :4], s[..., 4:]
    rr = np.sum(r * r, axis=-1, keepdims=True)
    d = (d - r * np.sum(r * d, axis=-1, keepdims=True) / rr) / np.sqrt(rr)
    return np.concatenate([r / np.sqrt(rr), d], axis=-1)


SCALES = [1.0, 1e3]


def clustered_sets(rng, batch, n, spread, scale=1.0):
    """(batch, n, 8) poses within rotation angle ``spread`` of a random centre per set."""
    centre = random_dqs(rng, (batch, 1), scale)
    offsets = dq.exp(0.5 * twists_near(rng, batch * n, spread, 0.5).reshape(batch, n, 6))
    return dq.mul(centre, offsets) * random_signs(rng, (batch, n))
