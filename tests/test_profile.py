"""service/profile.py: the trapezoid every move in the drivers and simulators runs on."""
import math

import numpy as np
import pytest

from dqpose.profile import Trapezoid, smoothstep


@pytest.mark.parametrize("length, speed, accel", [(1.0, 0.5, 2.0),     # trapezoid
                                                   (0.01, 0.5, 2.0),    # triangle
                                                   (0.125, 0.5, 2.0)])  # exactly touches speed
def test_trapezoid_against_its_derivatives(length, speed, accel):
    p = Trapezoid(length, speed, accel)
    t = np.linspace(0.0, p.duration, 20001)
    s = p(t)
    assert s[0] == 0.0 and s[-1] == length
    v = np.gradient(s, t)
    a = np.diff(s, 2) / (t[1] - t[0]) ** 2
    assert v.max() <= speed * (1 + 1e-6) and v.min() >= -1e-12
    assert np.abs(a).max() <= accel * (1 + 1e-3)
    assert np.isclose(v.max(), min(speed, math.sqrt(length * accel)), rtol=1e-3)
    # the closed form of the duration: cruise time plus one acceleration phase
    vp = min(speed, math.sqrt(length * accel))
    assert math.isclose(p.duration, length / vp + vp / accel)
    # rest at both ends, symmetric about the middle
    assert np.allclose(p(p.duration - t), length - s, atol=1e-12)


def test_trapezoid_is_clamped_and_scalar_in_scalar_out():
    p = Trapezoid(0.3, 0.2, 1.0)
    assert p(-1.0) == 0.0 and p(p.duration + 5) == 0.3
    assert isinstance(p(0.1), float) and p(np.array([0.1, 0.2])).shape == (2,)
    assert p.fraction(p.duration) == 1.0
    z = Trapezoid(0.0, 0.2, 1.0)
    assert z.duration == 0.0 and z(1.0) == 0.0 and z.fraction(0.0) == 1.0


@pytest.mark.parametrize("kw, name", [(dict(length=-1, speed=1, accel=1), "length"),
                                      (dict(length=1, speed=0, accel=1), "speed"),
                                      (dict(length=1, speed=1, accel=math.nan), "accel")])
def test_trapezoid_bad_arguments(kw, name):
    with pytest.raises(ValueError, match=f"^{name}:"):
        Trapezoid(**kw)


def test_smoothstep():
    s = np.linspace(0, 1, 1001)
    y = smoothstep(s)
    assert y[0] == 0 and y[-1] == 1 and np.all(np.diff(y) >= 0)
    assert np.allclose(np.gradient(y, s)[[0, -1]], 0, atol=5e-3)
    assert smoothstep(-3.0) == 0.0 and smoothstep(2.0) == 1.0 and smoothstep(0.5) == 0.5
