"""dqpose.lie against finite differences, closed-form identities, an independent SE(3) reference
(tests/reference.py, 4x4 matrices), Monte-Carlo covariance transport and, where installed, GTSAM."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dqpose import dq, lie
from tests import reference as ref

RNG = np.random.default_rng(20240607)


def twists(n, angle=None, rng=RNG):
    """n twists; rotation angles uniform in [0, 3) or all equal to ``angle``."""
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
    theta = rng.uniform(0, 3.0, size=n) if angle is None else np.full(n, float(angle))
    return np.concatenate([axis * theta[:, None], rng.normal(size=(n, 3))], axis=-1)


def numeric_jacobian(f, x, h=1e-6):
    """Central differences of f: (..., n) -> (..., m) at x, as (..., m, n)."""
    cols = []
    for k in range(x.shape[-1]):
        d = np.zeros(x.shape[-1])
        d[k] = h
        cols.append((f(x + d) - f(x - d)) / (2 * h))
    return np.stack(cols, axis=-1)


def Exp(xi):
    return lie.se3_exp(xi)


def Log(T):
    return lie.se3_log(T)


def mul(*Ts):
    out = Ts[0]
    for T in Ts[1:]:
        out = dq.mul(out, T)
    return out


def rot(w):
    """Rotation-only twists for the SO(3) checks."""
    return np.concatenate([w, np.zeros(w.shape[:-1] + (3,))], axis=-1)


# ---- hat / vee / Exp / Log / Ad -----------------------------------------------------------------
def test_hat_is_the_cross_product_and_vee_its_inverse():
    w, p = RNG.normal(size=(5, 3)), RNG.normal(size=(5, 3))
    assert np.allclose(np.einsum("nij,nj->ni", lie.so3_hat(w), p), np.cross(w, p), atol=1e-15)
    assert np.array_equal(lie.so3_vee(lie.so3_hat(w)), w)
    xi = twists(5)
    X = lie.se3_hat(xi)
    assert np.array_equal(X[:, 3], np.zeros((5, 4)))
    assert np.array_equal(lie.se3_vee(X), xi)


def test_exp_log_match_the_matrix_reference_and_the_half_twist_of_dq():
    xi = np.concatenate([twists(200), twists(5, 1e-8), twists(5, np.pi - 1e-6), twists(3, 0.0)])
    T = lie.se3_exp(xi)
    assert np.allclose(dq.to_matrix(T), ref.exp(xi), atol=1e-13)
    assert np.array_equal(T, dq.exp(xi / 2))
    assert np.allclose(lie.se3_log(T), xi, atol=1e-12)
    assert np.array_equal(lie.se3_log(T), 2 * dq.log(T))


def test_adjoint_conjugates_twists():
    T, xi = Exp(twists(50)), twists(50)
    A = lie.adjoint(T)
    M = dq.to_matrix(T)
    # Ad(T) xi^ = T xi^ T^-1
    assert np.allclose(lie.se3_hat(np.einsum("nij,nj->ni", A, xi)),
                       M @ lie.se3_hat(xi) @ np.linalg.inv(M), atol=1e-12)
    # Exp(Ad(T) xi) = T Exp(xi) T^-1
    assert np.allclose(dq.to_matrix(Exp(np.einsum("nij,nj->ni", A, xi))),
                       dq.to_matrix(mul(T, Exp(xi), dq.inv(T))), atol=1e-12)
    # a homomorphism, with Ad(T^-1) = Ad(T)^-1
    S = Exp(twists(50))
    assert np.allclose(lie.adjoint(dq.mul(T, S)), A @ lie.adjoint(S), atol=1e-12)
    assert np.allclose(lie.adjoint(dq.inv(T)) @ A, np.eye(6), atol=1e-12)


# ---- Jacobians ----------------------------------------------------------------------------------
JACOBIAN_ANGLES = [None, 1e-8, 0.05, 0.5, 2.0, np.pi - 1e-3, np.pi, 3.5]


@pytest.mark.parametrize("angle", JACOBIAN_ANGLES)
def test_se3_jacobians_match_finite_differences(angle):
    for xi in twists(4, angle):
        E = Exp(xi)
        # Exp(xi + d) = Exp(xi) Exp(Jr d) = Exp(Jl d) Exp(xi)
        Jr = numeric_jacobian(lambda x: Log(dq.mul(dq.inv(E), Exp(x))), xi)
        Jl = numeric_jacobian(lambda x: Log(dq.mul(Exp(x), dq.inv(E))), xi)
        assert np.allclose(lie.se3_right_jacobian(xi), Jr, atol=1e-8)
        assert np.allclose(lie.se3_left_jacobian(xi), Jl, atol=1e-8)
        if angle is None or angle < np.pi - 1e-4:  # Log wraps at pi: no derivative across it
            Jri = numeric_jacobian(lambda d: Log(dq.mul(E, Exp(d))), np.zeros(6))
            Jli = numeric_jacobian(lambda d: Log(dq.mul(Exp(d), E)), np.zeros(6))
            assert np.allclose(lie.se3_right_jacobian_inv(xi), Jri, atol=1e-7)
            assert np.allclose(lie.se3_left_jacobian_inv(xi), Jli, atol=1e-7)


@pytest.mark.parametrize("angle", JACOBIAN_ANGLES)
def test_so3_jacobians_are_the_rotation_blocks_and_match_finite_differences(angle):
    w = twists(4, angle)[:, :3]
    for f3, f6 in [(lie.so3_left_jacobian, lie.se3_left_jacobian),
                   (lie.so3_right_jacobian, lie.se3_right_jacobian),
                   (lie.so3_left_jacobian_inv, lie.se3_left_jacobian_inv),
                   (lie.so3_right_jacobian_inv, lie.se3_right_jacobian_inv)]:
        # the SE(3) ones are the C core's up to a rotation of pi (service/csrc/se3.c), the SO(3)
        # ones NumPy's: the same formulas, to rounding
        for block in (f6(rot(w))[:, :3, :3], f6(rot(w))[:, 3:, 3:]):
            np.testing.assert_allclose(block, f3(w), rtol=0, atol=1e-15 * np.abs(f3(w)).max())
    for wi in w:
        E = Exp(rot(wi))
        Jr = numeric_jacobian(lambda x: Log(dq.mul(dq.inv(E), Exp(rot(x))))[:3], wi)
        assert np.allclose(lie.so3_right_jacobian(wi), Jr, atol=1e-8)


@pytest.mark.parametrize("scale", [1e-9, 1e-3, 0.3, 0.49, 0.51, 1.5, 3.1])
def test_se3_jacobians_of_the_core_equal_numpys(scale):
    # The C core's (rotations up to pi) and NumPy's forms, both sides of the series' switch at
    # 0.5 rad: equal to rounding, so that the two paths of lie.py give one answer.
    rng = np.random.default_rng(7)
    xi = rng.normal(size=(50, 6))
    xi[:, :3] *= scale / np.linalg.norm(xi[:, :3], axis=1, keepdims=True)
    for sign in (1.0, -1.0):
        for core, numpy_form in ((lie._se3_jl_inv, lie._se3_jl_inv_numpy),
                                 (lie._se3_jl, lie._se3_jl_numpy)):
            got, want = core(xi, sign), numpy_form(xi, sign)
            assert lie._in_core(xi)
            scale = np.abs(want).max(axis=(1, 2))
            assert (np.abs(got - want).max(axis=(1, 2)) <= 2e-15 * scale).all()


def test_inverse_right_jacobian_matches_scipy_rotations():
    # moved from tests/drivers/test_camera.py with the Jacobian it tested
    rng = np.random.default_rng(3)
    for phi in [0.6 * rng.normal(size=3), 1e-8 * rng.normal(size=3), np.array([0.0, 3.0, 0.1])]:
        R0 = Rotation.from_rotvec(phi)
        num = np.zeros((3, 3))
        h = 1e-7
        for k in range(3):
            w = np.zeros(3)
            w[k] = h
            num[:, k] = ((R0 * Rotation.from_rotvec(w)).as_rotvec()
                         - (R0 * Rotation.from_rotvec(-w)).as_rotvec()) / (2 * h)
        assert np.allclose(lie.so3_right_jacobian_inv(phi), num, atol=1e-6)


@pytest.mark.parametrize("angle", JACOBIAN_ANGLES + [6.0])
def test_jacobian_identities(angle):
    xi = twists(20, angle)
    Jl, Jr = lie.se3_left_jacobian(xi), lie.se3_right_jacobian(xi)
    assert np.array_equal(Jr, lie.se3_left_jacobian(-xi))
    assert np.allclose(Jl @ lie.se3_left_jacobian_inv(xi), np.eye(6), atol=1e-11)
    assert np.allclose(Jr @ lie.se3_right_jacobian_inv(xi), np.eye(6), atol=1e-11)
    # Jl = Ad(Exp(xi)) Jr: independent of how either is computed
    assert np.allclose(Jl, lie.adjoint(Exp(xi)) @ Jr, atol=1e-12)
    w = xi[:, :3]
    assert np.allclose(lie.so3_left_jacobian(w) @ lie.so3_left_jacobian_inv(w), np.eye(3),
                       atol=1e-12)


def test_jacobians_at_tiny_angles_keep_full_precision():
    for theta in [0.0, 1e-300, 1e-12, 1e-8, 1e-5]:
        xi = twists(3, theta)
        w = xi[:, :3]
        K = lie.so3_hat(w)
        KK = K @ K
        # to second order the series are I +- K/2 + K^2/6 and I -+ K/2 + K^2/12, exact here
        assert np.allclose(lie.so3_left_jacobian(w), np.eye(3) + K / 2 + KK / 6, rtol=0, atol=1e-16)
        assert np.allclose(lie.so3_right_jacobian_inv(w), np.eye(3) + K / 2 + KK / 12, rtol=0,
                           atol=1e-16)
        for f in (lie.se3_left_jacobian, lie.se3_right_jacobian, lie.se3_left_jacobian_inv,
                  lie.se3_right_jacobian_inv):
            assert np.all(np.isfinite(f(xi)))
        # the translation block is v^/2 + O(theta |v|)
        assert np.allclose(lie.se3_left_jacobian(xi)[:, 3:, :3], lie.so3_hat(xi[:, 3:]) / 2,
                           atol=2 * theta + 1e-16)


def test_series_and_closed_forms_agree_where_they_meet():
    # the series serve angles below 0.5, the closed forms from 0.5 on: adjacent floats agree
    v = RNG.normal(size=3)
    for f in (lie.se3_left_jacobian, lie.se3_left_jacobian_inv):
        below = f(np.r_[np.nextafter(0.5, 0.0), 0.0, 0.0, v])
        at = f(np.r_[0.5, 0.0, 0.0, v])
        assert np.allclose(below, at, rtol=0, atol=1e-15)


def test_inverse_jacobians_do_not_exist_at_two_pi():
    with pytest.raises(ValueError, match=r"w: rotation angle 6.28.* multiple of 2 pi"):
        lie.so3_right_jacobian_inv([2 * np.pi, 0, 0])
    with pytest.raises(ValueError, match=r"xi\[1\]: rotation angle"):
        lie.se3_left_jacobian_inv([[0.1, 0, 0, 0, 0, 0], [0, 0, 2 * np.pi, 1, 0, 0]])
    assert np.all(np.isfinite(lie.se3_right_jacobian_inv([0, 0, 2 * np.pi - 1e-6, 1, 0, 0])))


# ---- broadcasting and errors --------------------------------------------------------------------
def test_every_function_broadcasts_over_leading_axes():
    xi = twists(6).reshape(2, 3, 6)
    for f in (lie.se3_left_jacobian, lie.se3_right_jacobian, lie.se3_left_jacobian_inv,
              lie.se3_right_jacobian_inv):
        out = f(xi)
        assert out.shape == (2, 3, 6, 6)
        assert np.array_equal(out[1, 2], f(xi[1, 2]))
    assert lie.so3_right_jacobian_inv(xi[..., :3]).shape == (2, 3, 3, 3)
    assert lie.se3_exp(xi).shape == (2, 3, 8) and lie.adjoint(Exp(xi)).shape == (2, 3, 6, 6)
    assert lie.se3_left_jacobian(np.zeros((0, 6))).shape == (0, 6, 6)
    T = Exp(twists(3))                              # (3, 8)
    S = np.stack([np.eye(6), 2 * np.eye(6)])[:, None]  # (2, 1, 6, 6)
    out = lie.cov_right_to_left(T, S)
    assert out.shape == (2, 3, 6, 6)
    assert np.allclose(out[1, 2], lie.cov_right_to_left(T[2], 2 * np.eye(6)))
    assert lie.cov_compose(S, T, None).shape == (2, 3, 6, 6)
    assert lie.cov_compose(None, T, np.eye(6)).shape == (3, 6, 6)


@pytest.mark.parametrize("call, message", [
    (lambda: lie.se3_exp(np.zeros(5)), r"xi: expected shape \(\.\.\., 6\), got \(5,\)"),
    (lambda: lie.se3_exp([0, 0, np.nan, 0, 0, 0]), "xi: contains NaN or infinity"),
    (lambda: lie.so3_left_jacobian("abc"), "w: expected numbers"),
    (lambda: lie.so3_vee(np.eye(4)), r"W: expected shape \(\.\.\., 3, 3\)"),
    (lambda: lie.se3_log(np.zeros(8)), "T: zero quaternion"),
    (lambda: lie.adjoint([[1.0] + [0] * 7, [2.0] + [0] * 7]), r"T\[1\]: quaternion norm 2"),
    (lambda: lie.cov_right_to_left(dq.identity(), np.eye(3)), r"cov: expected shape"),
    (lambda: lie.cov_inverse(dq.identity(), np.full((6, 6), np.inf)), "cov: contains NaN"),
    (lambda: lie.cov_compose(np.eye(6), np.ones(8), None), r"T_b: quaternion norm"),
    (lambda: lie.cov_compose(None, dq.identity(), np.eye(5)), r"cov_b: expected shape"),
    (lambda: lie.cov_compose(None, dq.identity(), None), "cov_a, cov_b: at least one"),
])
def test_bad_input_names_the_argument(call, message):
    with pytest.raises(ValueError, match=message):
        call()


# ---- covariance between frames ------------------------------------------------------------------
def random_covariance(rng, scale=1e-3):
    A = rng.normal(size=(6, 6)) * scale
    return A @ A.T + 1e-3 * scale ** 2 * np.eye(6)


def empirical_matches(samples, predicted):
    """The empirical covariance of zero-mean samples, whitened by the prediction, is ~I."""
    emp = samples.T @ samples / len(samples)
    L = np.linalg.cholesky(predicted)
    W = np.linalg.solve(L, np.linalg.solve(L, emp).T)
    return np.abs(W - np.eye(6)).max()


N_SAMPLES = 20000


def test_monte_carlo_covariance_transport():
    rng = np.random.default_rng(11)
    T, C = Exp(twists(1, 2.0, rng)[0]), Exp(twists(1, 1.0, rng)[0])
    S, S2 = random_covariance(rng), random_covariance(rng)
    xi = rng.multivariate_normal(np.zeros(6), S, size=N_SAMPLES)
    xi2 = rng.multivariate_normal(np.zeros(6), S2, size=N_SAMPLES)
    Tp = dq.mul(T, Exp(xi))  # samples of T with covariance S (right perturbation)
    # sampling error of the whitened entries is ~ 1/sqrt(N) = 0.007; a wrong frame is O(1) off
    tol = 0.04

    # right (body) -> left (world) and back
    left = Log(dq.mul(Tp, dq.inv(T)))
    assert empirical_matches(left, lie.cov_right_to_left(T, S)) < tol
    assert np.allclose(lie.cov_left_to_right(T, lie.cov_right_to_left(T, S)), S, atol=1e-18)
    # a constant pose on the right: T C
    body = Log(dq.mul(dq.inv(dq.mul(T, C)), dq.mul(Tp, C)))
    P = lie.cov_compose(S, C, None)
    assert empirical_matches(body, P) < tol
    AdCi = lie.adjoint(dq.inv(C))
    assert np.allclose(P, AdCi @ S @ AdCi.T, rtol=1e-14, atol=1e-20)
    assert empirical_matches(body, S) > 0.5  # the test can tell the frames apart
    # a constant pose on the left leaves the covariance as it was (exactly, not to first order)
    assert np.allclose(Log(dq.mul(dq.inv(dq.mul(C, T)), dq.mul(C, Tp))), xi, atol=1e-12)
    assert np.array_equal(lie.cov_compose(None, T, S), S)
    # two uncertain poses
    both = Log(dq.mul(dq.inv(dq.mul(T, C)), dq.mul(Tp, dq.mul(C, Exp(xi2)))))
    assert empirical_matches(both, lie.cov_compose(S, C, S2)) < tol
    # the inverse
    inv = Log(dq.mul(T, dq.inv(Tp)))  # right perturbation at T^-1: Log(T (T Exp(xi))^-1)
    assert empirical_matches(inv, lie.cov_inverse(T, S)) < tol


def ros_perturbation(T, Tp):
    """ROS's pose covariance vector of ``Tp`` about ``T``: translation difference, then the
    rotation vector of ``R' R^T`` (parent-frame axes)."""
    M, Mp = dq.to_matrix(T), dq.to_matrix(Tp)
    dt = Mp[..., :3, 3] - M[..., :3, 3]
    dtheta = Rotation.from_matrix(Mp[..., :3, :3] @ M[:3, :3].T).as_rotvec()
    return np.concatenate([dt, dtheta], axis=-1)


def test_ros_covariance_round_trips_and_matches_monte_carlo():
    rng = np.random.default_rng(22)
    # far from the origin: SE(3)'s full adjoint (t^ R coupling) would be O(1) off here
    T = dq.mul(dq.from_pose([1, 0, 0, 0], [3.0, -2.0, 1.5]), Exp(twists(1, 2.2, rng)[0]))
    S = random_covariance(rng)
    ros = lie.cov_to_ros(T, S)
    assert np.allclose(lie.cov_from_ros(T, ros), S, rtol=1e-14, atol=1e-20)
    assert np.allclose(lie.cov_to_ros(T, lie.cov_from_ros(T, ros)), ros, rtol=1e-14, atol=1e-20)
    assert np.allclose(ros, ros.T, atol=1e-20)
    xi = rng.multivariate_normal(np.zeros(6), S, size=N_SAMPLES)
    samples = ros_perturbation(T, dq.mul(T, Exp(xi)))
    assert empirical_matches(samples, ros) < 0.04
    # the test can tell the conventions apart: our order unconverted, the world-frame SE(3)
    # adjoint reordered
    assert empirical_matches(samples, S) > 0.5
    left = lie.cov_right_to_left(T, S)
    swap = np.block([[np.zeros((3, 3)), np.eye(3)], [np.eye(3), np.zeros((3, 3))]])
    assert empirical_matches(samples, swap @ left @ swap.T) > 0.5


def test_ros_covariance_broadcasts_and_names_bad_input():
    rng = np.random.default_rng(3)
    Ts = Exp(twists(4, rng=rng))
    S = np.stack([random_covariance(rng) for _ in range(4)])
    out = lie.cov_to_ros(Ts, S)
    assert out.shape == (4, 6, 6)
    assert np.allclose(out[2], lie.cov_to_ros(Ts[2], S[2]), rtol=1e-15, atol=0)
    with pytest.raises(ValueError, match=r"^cov: expected shape"):
        lie.cov_to_ros(Ts[0], np.eye(5))
    with pytest.raises(ValueError, match=r"^T"):
        lie.cov_from_ros(np.zeros(8), np.eye(6))


def test_covariance_maps_are_first_order_exact():
    # without sampling: the transported tangent vectors themselves, to O(|xi|^2)
    T, C = Exp(twists(1, 2.5)[0]), Exp(twists(1, 0.7)[0])
    xi = 1e-6 * RNG.normal(size=6)
    Tp = dq.mul(T, Exp(xi))
    assert np.allclose(Log(dq.mul(Tp, dq.inv(T))), lie.adjoint(T) @ xi, rtol=0, atol=1e-11)
    assert np.allclose(Log(dq.mul(dq.inv(dq.mul(T, C)), dq.mul(Tp, C))),
                       lie.adjoint(dq.inv(C)) @ xi, rtol=0, atol=1e-11)


def test_cov_sigmas_are_the_largest_standard_deviations_of_each_block():
    # independent: the worst direction's standard deviation of samples drawn from the covariance
    A = RNG.normal(size=(6, 6)) * np.array([0.01, 0.02, 0.005, 0.001, 0.003, 0.002])[:, None]
    cov = A @ A.T
    xs = RNG.multivariate_normal(np.zeros(6), cov, size=200_000)
    want = []
    for block in (xs[:, :3], xs[:, 3:]):
        _, _, vt = np.linalg.svd(block - block.mean(0), full_matrices=False)
        want.append(np.std(block @ vt[0]))
    got = lie.cov_sigmas(cov)
    np.testing.assert_allclose(got, want, rtol=0.01)
    # larger than any one axis' (the largest diagonal entry), broadcast over leading axes
    assert np.all(got >= np.sqrt([cov[:3, :3].diagonal().max(), cov[3:, 3:].diagonal().max()]))
    np.testing.assert_array_equal(lie.cov_sigmas(np.stack([cov, cov]))[1], got)
    np.testing.assert_array_equal(lie.cov_sigmas(np.diag([-1e-20] * 3 + [4.0] * 3)), [0.0, 2.0])
    with pytest.raises(ValueError, match=r"^cov: expected shape"):
        lie.cov_sigmas(np.eye(3))


# ---- GTSAM, where installed ---------------------------------------------------------------------
def test_matches_gtsam_pose3():
    gtsam = pytest.importorskip("gtsam")
    xi_all = np.concatenate([twists(30), twists(3, 1e-8), twists(3, np.pi - 1e-6)])
    for xi in xi_all:
        T = Exp(xi)
        P = gtsam.Pose3(dq.to_matrix(T))
        assert np.allclose(dq.to_matrix(T), gtsam.Pose3.Expmap(xi).matrix(), atol=1e-12)
        assert np.allclose(lie.adjoint(T), P.AdjointMap(), atol=1e-12)
        assert np.allclose(lie.se3_right_jacobian(xi), gtsam.Pose3.ExpmapDerivative(xi),
                           atol=1e-12)
        assert np.allclose(lie.se3_right_jacobian_inv(Log(T)), gtsam.Pose3.LogmapDerivative(P),
                           atol=1e-9)
        assert np.allclose(Log(T), gtsam.Pose3.Logmap(P), atol=1e-9)
