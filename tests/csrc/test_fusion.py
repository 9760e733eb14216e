"""The C fusion core (service/csrc/fusion.c, bound as ``_dqcore.fuse``) against the NumPy reference
(tests/fusion_reference.py) on random and hard problems, its batch axis, and its errors."""
import numpy as np
import pytest

from dqpose import _dqcore as _c
from dqpose import dq, lie
from dqpose.fusion.motion import Model, determined_without_each
from dqpose.fusion.process_noise import motion_solve
from tests import fusion_reference as ref
from tests.fusion._scenes import measure, random_cov, random_pose

FIELDS = ("mean", "covariance", "residuals", "distances", "nis", "tested", "status",
          "iterations", "chi2")


def core(Z, S, inlier=None, tol=1e-12, max_iter=100):
    return dict(zip(FIELDS, _c.fuse(Z, S, inlier, tol, max_iter)))


def assert_agrees(Z, S, inlier=None, tol=1e-12, max_iter=100, rel=1e-12):
    a = ref.fit(Z, S, inlier, tol, max_iter)
    b = core(Z, S, inlier, tol, max_iter)
    assert int(b["status"]) == a.status and int(b["iterations"]) == a.iterations
    assert np.array_equal(b["tested"], a.tested)
    assert np.abs(lie.se3_log(dq.mul(dq.conj(a.mean), b["mean"]))).max() < 1e-13
    scale = np.abs(a.covariance).max()
    assert np.abs(b["covariance"] - a.covariance).max() <= rel * scale
    assert np.array_equal(b["covariance"], b["covariance"].T)
    assert np.abs(b["residuals"] - a.residuals).max() < 1e-13
    # squared distances are a quadratic form in residuals of ~1e-3 with weights of ~1e6: an
    # absolute residual difference of 1e-16 is 1e-13 of them; relative to the largest
    big = max(1.0, a.distances.max())
    assert np.abs(b["distances"] - a.distances).max() <= 1e3 * rel * big
    assert np.abs(b["nis"] - a.nis).max() <= 1e4 * rel * max(1.0, a.nis.max())
    assert b["chi2"] == pytest.approx(a.chi2, rel=1e3 * rel, abs=1e-20)
    return b


@pytest.mark.parametrize("n", [1, 2, 3, 5, 10, 40])
def test_agrees_with_the_reference_on_random_problems(n):
    rng = np.random.default_rng(300 + n)
    for _ in range(20):
        S = np.array([random_cov(rng) for _ in range(n)])
        Z = measure(rng, random_pose(rng), S)
        b = assert_agrees(Z, S)
        assert b["mean"].shape == (8,) and b["covariance"].shape == (6, 6)
        assert b["residuals"].shape == (n, 6) and b["nis"].shape == (n,)


def test_agrees_on_inlier_subsets():
    """Outliers get residuals, distances and NIS against all inliers; the fit ignores them."""
    rng = np.random.default_rng(310)
    for _ in range(30):
        n = 8
        S = np.array([random_cov(rng) for _ in range(n)])
        Z = measure(rng, random_pose(rng), S)
        inlier = rng.random(n) < 0.6
        inlier[rng.integers(n)] = True
        b = assert_agrees(Z, S, inlier)
        Zm = Z.copy()
        for i in np.flatnonzero(~inlier):
            Zm[i] = random_pose(rng)
        c = core(Zm, S, inlier)
        assert np.array_equal(c["mean"], b["mean"])
        assert np.array_equal(c["covariance"], b["covariance"])


def test_agrees_far_apart():
    rng = np.random.default_rng(311)
    for _ in range(20):
        S = np.array([random_cov(rng, (20, 60), (0.3, 2.0)) for _ in range(5)])
        assert_agrees(measure(rng, random_pose(rng, 3.0), S), S)


def test_agrees_near_pi():
    """Residual rotations near pi: the closed forms of the Jacobian, not the series."""
    rng = np.random.default_rng(312)
    for k in range(10):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        # two measurements (89.5 + 0.05 k) deg either side of X about one axis, a third off it
        xi = np.zeros((3, 6))
        xi[:2, :3] = np.outer([1.0, -1.0], np.deg2rad(89.5 + 0.05 * k) * axis)
        xi[:2, 3:] = rng.normal(size=(2, 3)) * 0.1
        xi[2, :3], xi[2, 5] = rng.normal(size=3) * 0.3, 0.1
        Z = dq.mul(random_pose(rng), lie.se3_exp(xi))
        S = np.array([random_cov(rng, (30, 60), (0.05, 0.2)) for _ in range(3)])
        b = assert_agrees(Z, S)
        assert np.linalg.norm(b["residuals"][:2, :3], axis=1).max() > 1.5


def test_agrees_with_a_tiny_covariance():
    """One measurement 1e4 times more certain than the rest: its leave-one-out information is the
    others' (summed, not cancelled out of the total)."""
    rng = np.random.default_rng(313)
    for _ in range(20):
        S = np.array([random_cov(rng) for _ in range(5)])
        S[2] *= 1e-8
        b = assert_agrees(measure(rng, random_pose(rng), S), S)
        assert b["tested"].all()


def test_one_inlier_is_its_own_estimate():
    rng = np.random.default_rng(314)
    S = np.array([random_cov(rng) for _ in range(3)])
    Z = measure(rng, random_pose(rng), S)
    b = assert_agrees(Z, S, np.array([False, True, False]))
    assert np.array_equal(b["mean"], Z[1]) and int(b["iterations"]) == 0
    assert list(b["tested"]) == [True, False, True] and b["nis"][1] == 0.0


def test_step_limit_and_zero_steps():
    rng = np.random.default_rng(315)
    S = np.array([random_cov(rng, (20, 60), (0.3, 2.0)) for _ in range(5)])
    Z = measure(rng, random_pose(rng), S)
    for max_iter in (0, 1, 2):
        b = assert_agrees(Z, S, max_iter=max_iter)
        assert int(b["status"]) == 1 and int(b["iterations"]) == max_iter


def test_batch_axis_is_the_loop_over_problems():
    rng = np.random.default_rng(316)
    B, n = 7, 4
    S = np.array([[random_cov(rng) for _ in range(n)] for _ in range(B)])
    Z = np.array([measure(rng, random_pose(rng), s) for s in S])
    inlier = rng.random((B, n)) < 0.8
    inlier[:, 0] = True
    out = core(Z.reshape(B, 1, n, 8), S.reshape(B, 1, n, 6, 6), inlier.reshape(B, 1, n))
    assert out["mean"].shape == (B, 1, 8) and out["covariance"].shape == (B, 1, 6, 6)
    assert out["nis"].shape == (B, 1, n) and out["status"].shape == (B, 1)
    for k in range(B):
        one = core(Z[k], S[k], inlier[k])
        for f in FIELDS:
            assert np.array_equal(np.asarray(out[f])[k, 0], one[f]), f


def test_without_nis():
    rng = np.random.default_rng(317)
    S = np.array([random_cov(rng) for _ in range(4)])
    Z = measure(rng, random_pose(rng), S)
    full = _c.fuse(Z, S, None)
    lean = _c.fuse(Z, S, None, 1e-12, 100, False)
    assert lean[4] is None and lean[5] is None
    for k in (0, 1, 2, 3, 6, 7, 8):
        assert np.array_equal(full[k], lean[k])


def test_errors_name_the_argument_and_index():
    rng = np.random.default_rng(318)
    S = np.array([[random_cov(rng) for _ in range(3)] for _ in range(2)])
    Z = np.array([measure(rng, random_pose(rng), s) for s in S])
    bad = Z.copy()
    bad[1, 2, 0] = np.nan
    with pytest.raises(ValueError, match=r"poses\[1, 2\]: contains NaN"):
        _c.fuse(bad, S, None)
    bad = Z.copy()
    bad[0, 1] *= 1.1
    with pytest.raises(ValueError, match=r"poses\[0, 1\]: quaternion norm"):
        _c.fuse(bad, S, None)
    badS = S.copy()
    badS[1, 0] -= 2.0 * np.abs(badS[1, 0]).max() * np.eye(6)
    with pytest.raises(ValueError, match=r"covariances\[1, 0\]: not positive definite"):
        _c.fuse(Z, badS, None)
    badS = S.copy()
    badS[0, 2, 3, 3] = np.inf
    with pytest.raises(ValueError, match=r"covariances\[0, 2\]: contains NaN"):
        _c.fuse(Z, badS, None)
    with pytest.raises(ValueError, match=r"inliers\[1\]: selects no measurement"):
        _c.fuse(Z, S, np.array([[True, False, False], [False, False, False]]))
    with pytest.raises(ValueError, match=r"covariances: expected shape \(\.\.\., n, 6, 6\)"):
        _c.fuse(Z, S[:, :2], None)
    with pytest.raises(ValueError, match=r"poses: expected shape \(\.\.\., n, 8\)"):
        _c.fuse(Z[..., :7], S, None)
    with pytest.raises(ValueError, match=r"inliers: expected shape"):
        _c.fuse(Z, S, np.ones(3, bool))
    with pytest.raises(ValueError, match="poses: no measurements"):
        _c.fuse(Z[:, :0], S[:, :0], None)
    with pytest.raises(ValueError, match="tol: must be finite"):
        _c.fuse(Z, S, None, np.nan)
    with pytest.raises(ValueError, match="max_iter: must be >= 0"):
        _c.fuse(Z, S, None, 1e-12, -1)


# ---- the constant-twist time-aligned fit (dq_motion_fit, bound as _dqcore.motion_fit) ---------
MOTION = ("mean", "twist", "ell", "H", "chi2", "status", "iterations", "dt", "residuals", "cost",
          "G", "nis", "tested", "P")


def motion_scene(rng, n, estimate=(True, True), twist_prior=False, one_instant=False,
                 cov=random_cov):
    """n measurements of a body on a screw by three sources (latencies 20, 5, 0 ms; the first two
    estimated from 30 ± 10 and 0 ± 10 ms where ``estimate`` says), stamped over 0.1 s before the
    fusion time 0: the poses, covariances and the model of dqpose.fusion."""
    X0, V0 = random_pose(rng), rng.normal(size=6) * np.array([1, 1, 1, 0.3, 0.3, 0.3])
    source = np.arange(n) % 3
    truth = np.array([0.02, 0.005, 0.0])[source]
    stamp = (np.full(n, -0.04) if one_instant else -rng.uniform(0.0, 0.1, n)) + truth
    S = np.array([cov(rng) for _ in range(n)])
    Z = measure(rng, dq.mul(X0, lie.se3_exp((stamp - truth)[:, None] * V0)), S)
    slots = [k for k, e in enumerate(estimate) if e]
    slot = np.array([slots.index(s) if s in slots else -1 for s in source])
    model = Model(stamp=stamp, latency=truth, slot=slot,
                          prior=np.array([0.03, 0.0])[slots], prior_w=np.full(len(slots), 1e4),
                          twist=True, twist_w=np.linalg.inv(np.diag([1, 1, 1, 0.1, 0.1, 0.1]) ** 2)
                          if twist_prior else None)
    return Z, S, model


def motion_core(Z, S, model, inlier, start, tested, tol=1e-12, max_iter=100, jacobians=True):
    return dict(zip(MOTION, _c.motion_fit(Z, S, inlier, start, model.stamp, model.latency,
                                          model.slot, model.prior, model.prior_w, model.twist,
                                          model.twist_w, tested, tol, max_iter, jacobians)))


def assert_motion_agrees(Z, S, model, inlier=None, tol=1e-12, max_iter=100, rel=1e-12):
    n = Z.shape[0]
    inlier = np.ones(n, bool) if inlier is None else inlier
    tested = ~inlier | ref.determined_without_each(model, inlier)
    a = ref.motion_fit(Z, S, model, inlier, ref.motion_start(Z, model, inlier), tested, tol,
                       max_iter)
    # the C fit picks its start and the tested measurements itself
    b = motion_core(Z, S, model, inlier, None, True, tol, max_iter)
    assert np.array_equal(b["tested"], tested)
    assert int(b["status"]) == a.status and int(b["iterations"]) == a.iterations
    assert np.abs(lie.se3_log(dq.mul(dq.conj(a.mean), b["mean"]))).max() < 1e3 * rel
    assert np.abs(b["twist"] - a.twist).max() <= 1e3 * rel * max(1.0, np.abs(a.twist).max())
    assert np.abs(b["ell"] - a.ell).max(initial=0.0) <= 1e2 * rel
    # the information spans the pose's, the twist's (dt² smaller) and the latencies'
    d = np.sqrt(np.diag(a.H))
    assert np.abs((b["H"] - a.H) / np.outer(d, d)).max() <= 10 * rel
    assert np.array_equal(b["H"], b["H"].T)
    assert np.abs(b["dt"] - a.dt).max() <= 1e2 * rel
    assert np.abs(b["residuals"] - a.residuals).max() < 1e3 * rel
    assert np.abs(b["G"] - a.G).max() <= 10 * rel * np.abs(a.G).max()
    big = max(1.0, a.cost.max())
    assert np.abs(b["cost"] - a.cost).max() <= 1e3 * rel * big
    assert b["chi2"] == pytest.approx(a.chi2, rel=1e3 * rel, abs=1e-20)
    assert np.abs(b["nis"] - a.nis).max() <= 1e4 * rel * max(1.0, a.nis.max())
    assert np.array_equal(b["nis"] == 0.0, ~tested | (a.nis == 0.0))
    assert np.array_equal(b["P"], b["P"].T)
    assert np.abs(b["P"] @ b["H"] - np.eye(model.dim)).max() < 1e-6
    return b


@pytest.mark.parametrize("n", [5, 7, 20, 90])
@pytest.mark.parametrize("estimate", [(False, False), (True, False), (True, True)])
def test_motion_fit_agrees_with_the_reference(n, estimate):
    rng = np.random.default_rng(400 + n + 7 * sum(estimate))
    for trial in range(6):
        Z, S, model = motion_scene(rng, n, estimate, twist_prior=trial % 2 == 1)
        b = assert_motion_agrees(Z, S, model)
        assert int(b["status"]) == 0 and b["H"].shape == (model.dim, model.dim)
        assert b["ell"].shape == (sum(estimate),) and b["G"].shape == (n, 6, model.dim)


def test_motion_fit_starts_from_the_data_twist_and_saves_an_iteration():
    """A body moving on a screw: the C fit starts its twist from the motion between the inliers
    taken first and last (``motion_twist_start``), so it converges in fewer Gauss-Newton
    iterations than the same loop started at rest, to the same answer."""
    rng = np.random.default_rng(420)
    saved = []
    for _ in range(8):
        # 60 measurements over 1 s (30 Hz from two cameras), 0.3° and 1 mm
        n = 60
        X0, V0 = random_pose(rng), rng.normal(size=6) * 0.2
        stamp = -np.repeat(np.arange(n // 2), 2) / 30.0
        S = np.broadcast_to(np.diag([np.deg2rad(0.3)] * 3 + [1e-3] * 3) ** 2, (n, 6, 6)).copy()
        Z = measure(rng, dq.mul(X0, lie.se3_exp(stamp[:, None] * V0)), S)
        model = Model(stamp=stamp, latency=np.zeros(n), slot=np.full(n, -1),
                              prior=np.zeros(0), prior_w=np.zeros(0), twist=True, twist_w=None)
        inlier = np.ones(n, bool)
        W = np.linalg.inv(S)
        start = ref.motion_start(Z, model, inlier)
        X, V, _, _, rest = motion_solve(Z, model, start, np.zeros(6),
                                                model.prior.copy(), 1e-12, 100, W)
        b = motion_core(Z, S, model, inlier, None, None)
        assert np.abs(b["twist"] - V).max() <= 1e-9 * max(1.0, np.abs(V).max())
        saved.append(rest - int(b["iterations"]))
    assert min(saved) >= 0 and sum(saved) >= len(saved) // 2, saved


def test_motion_fit_agrees_on_inlier_subsets_and_ignores_the_outliers():
    rng = np.random.default_rng(410)
    for _ in range(20):
        n = 12
        Z, S, model = motion_scene(rng, n, twist_prior=bool(rng.integers(2)))
        inlier = rng.random(n) < 0.7
        inlier[:3] = True  # two instants at least, every source
        b = assert_motion_agrees(Z, S, model, inlier)
        Zm = Z.copy()
        Zm[~inlier] = random_pose(rng)
        c = motion_core(Zm, S, model, inlier, None, None)
        for k in ("mean", "twist", "ell", "H", "chi2", "P"):
            assert np.array_equal(c[k], b[k]), k
        assert c["nis"] is None and c["tested"] is None


def test_motion_fit_agrees_near_pi():
    """Residual rotations near pi (the closed forms of Jl⁻¹, not the series): at each of two
    instants two measurements (89.5 + 0.05 k)° either side of the prediction about one axis."""
    rng = np.random.default_rng(412)
    for k in range(10):
        Z, S, model = motion_scene(rng, 6, twist_prior=True,
                                   cov=lambda r: random_cov(r, (30, 60), (0.05, 0.2)))
        model = Model(np.array([-0.05, -0.05, 0.0, 0.0, -0.05, 0.0]), np.zeros(6),
                              model.slot, model.prior, model.prior_w, True, model.twist_w)
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        xi = rng.normal(size=(6, 6)) * 0.05
        xi[:4, :3] = np.outer([1.0, -1.0, 1.0, -1.0], np.deg2rad(89.5 + 0.05 * k) * axis)
        Z = dq.mul(Z[np.array([4, 4, 5, 5, 4, 5])], lie.se3_exp(xi))
        b = assert_motion_agrees(Z, S, model, rel=1e-11)
        assert np.linalg.norm(b["residuals"][:, :3], axis=1).max() > 1.5


def test_motion_fit_agrees_with_a_tiny_covariance():
    """One measurement 1e4 times more certain than the rest: the others' leave-one-out
    information is summed, not its subtracted from the total. Its σ of ~1e-7 leaves the state
    determined only to rounding amplified by cond(H) ~ 1e10: the two fits (run to the step limit,
    so that neither stops at a different step below tol) agree to 1e-7 of the state's σ and the
    information and the NIS to ~1e-8 and ~1e-5, not 1e-12."""
    rng = np.random.default_rng(413)
    for _ in range(10):
        Z, S, model = motion_scene(rng, 10, twist_prior=True)
        S[4] *= 1e-8
        Z[4] = measure(rng, Z[4], S[4:5])[0]
        inlier = tested = np.ones(10, bool)
        start = ref.motion_start(Z, model, inlier)
        a = ref.motion_fit(Z, S, model, inlier, start, tested, 0.0, 12)
        b = motion_core(Z, S, model, inlier, start, tested, 0.0, 12)
        d = np.concatenate([lie.se3_log(dq.mul(dq.conj(a.mean), b["mean"])),
                            b["twist"] - a.twist, b["ell"] - a.ell])
        assert np.abs(d / np.sqrt(np.diag(np.linalg.inv(a.H)))).max() < 1e-6
        scale = np.sqrt(np.diag(a.H))
        assert np.abs((b["H"] - a.H) / np.outer(scale, scale)).max() < 1e-7
        assert np.abs(b["nis"] - a.nis).max() < 1e-4 * a.nis.max()
        assert b["chi2"] == pytest.approx(a.chi2, rel=1e-5)
        assert (b["nis"] > 0).all()


def test_motion_fit_of_one_instant_with_a_twist_prior():
    """All taken at one instant 40 ms before the fusion time: the twist comes from its prior
    alone, and the leave-one-out NIS is defined for every measurement."""
    rng = np.random.default_rng(414)
    for _ in range(10):
        Z, S, model = motion_scene(rng, 6, (False, False), twist_prior=True, one_instant=True)
        b = assert_motion_agrees(Z, S, model)
        assert np.abs(b["dt"] + 0.04).max() < 1e-15 and (b["nis"] > 0).all()


def test_motion_fit_step_limit():
    rng = np.random.default_rng(415)
    Z, S, model = motion_scene(rng, 20)
    for max_iter in (0, 1, 2):
        b = assert_motion_agrees(Z, S, model, max_iter=max_iter)
        assert int(b["status"]) == 1 and int(b["iterations"]) == max_iter


def test_motion_fit_errors():
    rng = np.random.default_rng(416)
    Z, S, model = motion_scene(rng, 6)
    start, ones = Z[0], np.ones(6, bool)

    def call(Z=Z, S=S, inlier=None, start=start, slot=model.slot, twist_w=None, tested=ones):
        return _c.motion_fit(Z, S, inlier, start, model.stamp, model.latency, slot, model.prior,
                             model.prior_w, True, twist_w, tested)

    bad = S.copy()
    bad[2] -= 2.0 * np.abs(bad[2]).max() * np.eye(6)
    with pytest.raises(ValueError, match=r"covariances\[2\]: not positive definite"):
        call(S=bad)
    bad = Z.copy()
    bad[3, 0] = np.nan
    with pytest.raises(ValueError, match=r"poses\[3\]: contains NaN"):
        call(Z=bad)
    bad = Z.copy()
    bad[1] *= 1.1
    with pytest.raises(ValueError, match=r"poses\[1\]: quaternion norm"):
        call(Z=bad)
    with pytest.raises(ValueError, match=r"start: quaternion norm"):
        call(start=2 * start)
    with pytest.raises(ValueError, match="inliers: selects no measurement"):
        call(inlier=np.zeros(6, bool))
    # one instant without a twist prior: the twist is not determined
    with pytest.raises(ValueError, match="information is not positive definite"):
        call(inlier=np.array([True, False, False, False, False, False]))
    with pytest.raises(ValueError, match=r"slots\[0\]: 2 is not -1 or a latency index"):
        call(slot=np.full(6, 2))
    with pytest.raises(ValueError, match=r"covariances: expected shape \(6, 6, 6\)"):
        call(S=S[:5])
    with pytest.raises(ValueError, match=r"twist_information: expected shape \(6, 6\)"):
        call(twist_w=np.eye(5))
    with pytest.raises(ValueError, match=r"poses: expected shape \(n, 8\)"):
        call(Z=Z[:, :7])


def test_determined_without_each_agrees_with_the_reference_on_shared_instants():
    """Measurements taken at a few shared instants (times drawn from three values), random
    inlier sets (none, one, all included): the C count of instants and of the inliers alone at
    theirs against the NumPy one, with a twist to find, with a prior on it, and with none."""
    rng = np.random.default_rng(417)
    for trial in range(300):
        n = int(rng.integers(1, 9))
        stamp = rng.choice([-0.02, -0.01, 0.0], n) + rng.choice([0.0, 0.005], n)
        latency = np.where(rng.random(n) < 0.5, 0.005, 0.0)
        inlier = rng.random(n) < [0.0, 0.3, 0.7, 1.0][trial % 4]
        for twist, prior in ((True, None), (True, np.eye(6)), (False, None)):
            model = Model(stamp, latency, np.full(n, -1), np.zeros(0), np.zeros(0),
                                  twist, prior)
            got = determined_without_each(model, inlier)
            assert got.dtype == bool
            assert np.array_equal(got, ref.determined_without_each(model, inlier)), (
                stamp - latency, inlier, twist, prior is not None)


def test_motion_fit_picks_its_start_only_when_it_estimates_a_twist():
    rng = np.random.default_rng(418)
    Z, S, model = motion_scene(rng, 6)
    with pytest.raises(ValueError, match="start: needed when no twist is estimated"):
        _c.motion_fit(Z, S, None, None, model.stamp, model.latency, model.slot, model.prior,
                      model.prior_w, False, None, None)
    with pytest.raises(ValueError, match="inliers: selects no measurement"):
        _c.motion_fit(Z, S, np.zeros(6, bool), None, model.stamp, model.latency, model.slot,
                      model.prior, model.prior_w, True, None, True)
