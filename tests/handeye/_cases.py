"""Shared by the hand-eye tests: every setup with every scene geometry, poses equal up to sign, the
NEES of an estimate, and a reading as its setup gives it."""
import numpy as np

from dqpose import dq, lie
from tests import _handeye as H

CASES = [(setup, geometry) for setup in H.SETUPS for geometry in H.GEOMETRIES]


def _close(a, b, tol):
    """Poses equal up to sign, to ``tol`` in every component."""
    a, b = np.asarray(a), np.asarray(b)
    s = np.where((a[..., :4] * b[..., :4]).sum(-1, keepdims=True) < 0, -1.0, 1.0)
    return np.max(np.abs(a - s * b)) < tol


def _nees(estimate, truth, cov):
    xi = lie.se3_log(dq.mul(dq.inv(estimate), truth))
    return float(xi @ np.linalg.solve(cov, xi))


def _reading(F, setup):
    return F if setup == "eye_in_hand" else dq.inv(F)
