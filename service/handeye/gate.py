"""The χ² gate's thresholds: what a genuine sample's NIS exceeds with probability ``1 − _GATE``.

With the noise given the NIS of a genuine sample is χ²₆ (its standardised residual, or its
prediction when left out). With the noise estimated it is studentised by an estimate of the
noise, and χ²₆ is the wrong law (Cook & Weisberg, *Residuals and Influence in Regression*, 1982,
§2.2.1, for one variance; the three components are taken here as one scale with the residual
degrees of freedom ``ν = 6m − 12`` of the ``m`` samples fitted):

* a sample left out is judged against a noise estimated without it: ``NIS = 6 F(6, ν)``;
* a sample in the fit is judged against a noise estimated with it (internally studentised): its
  own residual is part of the estimate, so ``NIS / ν`` is ``Beta(3, (ν − 6) / 2)``, bounded by
  ``ν`` and lighter-tailed than χ²₆. At the χ²₆ quantile the gate rejected 0.036 % of genuine
  samples (29 of 80,000 in 4,000 healthy 20-pose scenes) against its 0.1 %, and a sample whose
  error inflates the estimate hides itself the more.

Both tend to χ²₆ as ``ν`` grows.
"""
from __future__ import annotations

import math
from functools import lru_cache

_GATE = 0.999                          # χ² probability of the robust gate
GATE_6 = 22.457744484825192           # χ²₆ quantile at _GATE (fusion.chi2_quantile(0.999, 6))
GATE_3 = 16.266236196238010           # χ²₃ quantile at _GATE


def _beta_fraction(a: float, b: float, x: float) -> float:
    """The continued fraction of the regularised incomplete beta function (modified Lentz)."""
    tiny = 1e-300
    c, d = 1.0, 1.0 - (a + b) * x / (a + 1.0)
    d = 1.0 / (tiny if abs(d) < tiny else d)
    h = d
    for m in range(1, 10000):
        for num in (m * (b - m) * x / ((a + 2 * m - 1) * (a + 2 * m)),
                    -(a + m) * (a + b + m) * x / ((a + 2 * m) * (a + 2 * m + 1))):
            d = 1.0 + num * d
            d = 1.0 / (tiny if abs(d) < tiny else d)
            c = 1.0 + num / c
            c = tiny if abs(c) < tiny else c
            h *= d * c
        if abs(d * c - 1.0) < 1e-15:
            break
    return h


def _beta_cdf(a: float, b: float, x: float) -> float:
    """``I_x(a, b)``, the regularised incomplete beta function."""
    if x <= 0.0:
        return 0.0
    if x >= 1.0:
        return 1.0
    front = math.exp(math.lgamma(a + b) - math.lgamma(a) - math.lgamma(b)
                     + a * math.log(x) + b * math.log1p(-x))
    if x < (a + 1.0) / (a + b + 2.0):
        return front * _beta_fraction(a, b, x) / a
    return 1.0 - front * _beta_fraction(b, a, 1.0 - x) / b


@lru_cache(maxsize=1024)
def _beta_quantile(a: float, b: float, probability: float) -> float:
    lo, hi = 0.0, 1.0
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        if _beta_cdf(a, b, mid) < probability:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def thresholds(estimated: bool, dof: int) -> tuple[float, float]:
    """``(in the fit, left out)``: the NIS thresholds of the gate at probability ``_GATE`` for a
    sample in the fit and for one left out of it; ``dof`` the residual degrees of freedom of the
    fit (``6m − 12``) when the noise is estimated (see the module docstring)."""
    if not estimated or dof > 100_000:
        return GATE_6, GATE_6
    if dof <= 6:
        # A fit with no spare degrees of freedom tells nothing about a sample in it; one left
        # out is judged by an F with so few that only a gross error passes the bound.
        return math.inf, math.inf
    x_in = _beta_quantile(3.0, 0.5 * (dof - 6), _GATE)
    x_out = _beta_quantile(3.0, 0.5 * dof, _GATE)
    return dof * x_in, dof * x_out / (1.0 - x_out)
