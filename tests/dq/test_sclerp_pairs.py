"""ScLERP of independent pairs from Python (``dq.sclerp`` of same-shape arrays, the vectorised path
that checks each block of 64 pairs as it interpolates it): every pair's result is the one it has
alone, wherever in the batch it is and whatever its neighbours need (normalising, a tau beyond
the kernel's range); a bad pose, tau or result in a later block is named by its index."""
import numpy as np
import pytest

from dqpose import dq

N = 200         # four blocks of the kernel, the last one short


@pytest.fixture
def pairs():
    rng = np.random.default_rng(7)
    a = dq.exp(rng.normal(size=(N, 6)) * 0.7)
    b = dq.mul(a, dq.exp(rng.normal(size=(N, 6)) * 0.5))
    tau = rng.uniform(-0.5, 1.5, size=N)
    a[70] = np.round(a[70], 4)          # within the tolerance, not unit: normalised
    b[140, 4:] += 1e-5 * a[140, :4]     # a dual part not orthogonal (within the tolerance)
    tau[141] = 3e5                      # beyond the block kernel's sin/cos range
    return a, b, tau


def alone(a, b, tau):
    """The pair's result in a batch of copies of itself (the same path, nothing beside it)."""
    n = 16
    return dq.sclerp(np.tile(a, (n, 1)), np.tile(b, (n, 1)), np.full(n, tau))[0]


def test_each_pair_gives_what_it_gives_alone(pairs):
    a, b, tau = pairs
    out = dq.sclerp(a, b, tau)
    for i in (0, 63, 64, 70, 71, 140, 141, 199):
        np.testing.assert_array_equal(out[i], alone(a[i], b[i], tau[i]), err_msg=str(i))
    # and the same poses as the one-pair path (another algorithm: to rounding)
    for i in range(N):
        one = dq.sclerp(a[i], b[i], tau[i])
        assert min(np.abs(out[i] - one).max(), np.abs(out[i] + one).max()) < 1e-9 * max(
            1.0, np.abs(one).max()), i
    assert dq.sclerp(a[:1].repeat(N, 0), b[:1].repeat(N, 0), tau).shape == (N, 8)


@pytest.mark.parametrize("bad,message", [
    (lambda a, b, t: a.__setitem__((150, 2), np.nan), r"^a\[150\]: contains NaN or infinity"),
    (lambda a, b, t: b.__setitem__(150, 1.01 * b[150]), r"^b\[150\]: quaternion norm 1\.01 is "),
    (lambda a, b, t: t.__setitem__(150, np.inf), r"^tau\[150\]: contains NaN or infinity"),
    (lambda a, b, t: (a.__setitem__(150, dq.exp([0.1, 0, 0, 10.0, 0, 0])),
                      b.__setitem__(150, dq.identity()), t.__setitem__(150, 1e308)),
     r"^tau\[150\]: result is not finite"),
])
def test_a_bad_element_in_a_later_block_is_named(pairs, bad, message):
    a, b, tau = (x.copy() for x in pairs)
    bad(a, b, tau)
    with pytest.raises(ValueError, match=message):
        dq.sclerp(a, b, tau)
