"""χ² quantiles without SciPy (the core does not depend on it): the robust mode's gate and each
source's consistency interval are quantiles of χ² with 6 (one measurement's NIS) or 6 k (k of
them summed) degrees of freedom.
"""
from __future__ import annotations

import math
from functools import lru_cache

from dqpose.errors import FieldError

#: the χ² probability of the robust gate and of a fused pose's consistency verdict
DEFAULT_PROBABILITY = 0.999


def gamma_p(a: float, x: float) -> float:
    """The regularised lower incomplete gamma function P(a, x) (series / continued fraction)."""
    if x <= 0.0:
        return 0.0
    log_front = a * math.log(x) - x - math.lgamma(a)
    if x < a + 1.0:
        term = total = 1.0 / a
        k = a
        while abs(term) > abs(total) * 1e-17:
            k += 1.0
            term *= x / k
            total += term
        return min(1.0, total * math.exp(log_front))
    # Lentz's continued fraction for Q(a, x)
    tiny = 1e-300
    b = x + 1.0 - a
    c, d = 1.0 / tiny, 1.0 / b
    h = d
    for i in range(1, 100000):
        an = -i * (i - a)
        b += 2.0
        d = an * d + b
        d = tiny if abs(d) < tiny else d
        c = b + an / c
        c = tiny if abs(c) < tiny else c
        d = 1.0 / d
        delta = d * c
        h *= delta
        if abs(delta - 1.0) < 1e-16:
            break
    return max(0.0, 1.0 - math.exp(log_front) * h)


@lru_cache(maxsize=256)
def chi2_quantile(probability: float, dof: int) -> float:
    """The ``probability`` quantile of the χ² distribution with ``dof`` degrees of freedom."""
    if not 0.0 < probability < 1.0:
        raise FieldError("probability", f"must be within (0, 1), got {probability!r}")
    if dof < 1:
        raise FieldError("dof", f"must be >= 1, got {dof!r}")
    a = 0.5 * dof
    lo, hi = 0.0, max(1.0, float(dof))
    while gamma_p(a, 0.5 * hi) < probability:
        lo, hi = hi, 2.0 * hi
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if mid in (lo, hi):
            break
        if gamma_p(a, 0.5 * mid) < probability:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)
