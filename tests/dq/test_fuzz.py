"""dqpose.dq under garbage input: every function returns finite values or raises ValueError."""
from __future__ import annotations

import numpy as np
import pytest

from dqpose import dq
from tests.conftest import random_dqs, random_quaternions

# ---- fuzz ---------------------------------------------------------------------------------------

SPECIAL = np.array([np.nan, np.inf, -np.inf, 1e300, -1e300, 1e-300, 5e-324, 0.0, -0.0, 1e154,
                    1e-160, 1.0 + 0.99 * dq.UNIT_TOL, 1.0 + 1.01 * dq.UNIT_TOL])


def _garbage(rng, core, lead):
    """Mostly valid values with a few poisoned entries, sometimes pure noise."""
    shape = lead + core
    kind = rng.integers(0, 4)
    if core == (8,) or core == (None, 8):
        x = random_dqs(rng, shape[:-1], 10.0 ** rng.integers(-3, 4))
    elif core == (4, 4):
        x = (dq.to_matrix(random_dqs(rng, lead, 10.0 ** rng.integers(-3, 4))) if kind
             else rng.normal(size=shape))
    elif core == (4,):
        x = random_quaternions(rng, lead)
    else:
        x = rng.normal(size=shape) * 10.0 ** rng.integers(-3, 4)
    x = np.array(x, dtype=float)
    if kind == 0:
        x = rng.normal(size=x.shape) * 10.0 ** rng.integers(-300, 300)
    if x.size and kind in (1, 2):
        flat = x.reshape(-1)
        idx = rng.integers(0, flat.size, rng.integers(1, 4))
        with np.errstate(invalid="ignore", over="ignore"):
            flat[idx] = (rng.choice(SPECIAL, idx.size) if kind == 1
                         else flat[idx] * rng.choice(SPECIAL, idx.size))
    return x


FUZZ_SPECS = [  # (function, core shapes of its arguments; None = set size)
    (dq.mul, [(8,), (8,)]), (dq.conj, [(8,)]), (dq.normalize, [(8,)]), (dq.log, [(8,)]),
    (dq.exp, [(6,)]), (dq.power, [(8,), ()]), (dq.from_matrix, [(4, 4)]), (dq.to_matrix, [(8,)]),
    (dq.from_pose, [(4,), (3,)]), (dq.to_pose, [(8,)]), (dq.transform, [(8,), (3,)]),
    (dq.screw, [(8,)]), (dq.sclerp, [(8,), (8,), ()]),
    (dq.dlb, [(None, 8), (None,)]), (dq.dib, [(None, 8), (None,)]), (dq.lin, [(None, 8), (None,)]),
    (dq.dec, [(None, 8), (None,)]), (dq.logblend, [(None, 8), (None,)]),
    (lambda q, w: dq.blend(q, w, method="sclerp"), [(2, 8), (2,)]),
]


@pytest.mark.parametrize("f,cores", FUZZ_SPECS, ids=lambda v: getattr(v, "__name__", None))
def test_fuzz_returns_finite_or_raises_value_error(rng, f, cores):
    for _ in range(300):
        lead = tuple(int(k) for k in rng.integers(1, 4, rng.integers(0, 3)))
        n = int(rng.integers(1, 5))
        args = []
        for core in cores:
            core = tuple(n if c is None else c for c in core)
            if rng.random() < 0.05:  # a wrong core shape now and then
                core = core[:-1] + (core[-1] + 1,) if core else (2,)
            arg_lead = lead[int(rng.integers(0, len(lead) + 1)):]
            if core in ((n, 8), (2, 8)):
                x = _garbage(rng, (8,), arg_lead + core[:-1])
            else:
                x = _garbage(rng, core, arg_lead)
                if cores[-1] in ((None,), (2,)) and rng.random() < 0.8:
                    x = np.abs(x)  # mostly valid weights, so the blends themselves get exercised
            args.append(x)
        try:
            out = f(*args)
        except ValueError as e:
            assert str(e).split(":")[0].split("[")[0] in (
                "a", "b", "x", "tau", "T", "q", "t", "p", "dqs", "weights",
                "shape mismatch"), str(e)
            continue
        outs = out if isinstance(out, tuple) else (out,)
        for o in outs:
            assert np.all(np.isfinite(o)), (f, args, out)
