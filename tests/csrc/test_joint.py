"""The joint fit with uncertain extrinsics in C (``dq_joint_fit``, bound as
``_dqcore.joint_fit``, called by ``dqpose.fusion.extrinsics.joint_fit``) against its NumPy
reference (tests/fusion_reference.py) on random multi-part problems, and its argument checks."""
import numpy as np
import pytest

from dqpose import _dqcore as _c
from dqpose import dq, lie
from dqpose.fusion.extrinsics import Extrinsics, Part, joint_fit, static_model
from dqpose.fusion.motion import Model
from tests import fusion_reference as ref
from tests.fusion._scenes import measure, random_cov, random_pose

# the sources: (uncertain extrinsic, latency estimated, configured latency)
SOURCES = ((True, True, 0.02), (True, False, 0.005), (False, True, 0.0), (True, True, 0.01))


def near_pi(rng):
    """A pose turned by π less up to 1e-3 rad about a random axis."""
    axis = rng.normal(size=3)
    return lie.se3_exp(np.r_[(np.pi - 1e-3 * rng.random()) * axis / np.linalg.norm(axis),
                             rng.normal(size=3)])


def problem(rng, parts=3, per=8, outliers=False, one_instant=(), twist_prior=(),
            cov=random_cov, ext_cov=None, pose=random_pose):
    """Bodies each seen over 0.1 s by a few of SOURCES (the uncertain ones sharing one error
    per source, the estimated latencies shared by every body a source sees), world-frame
    measurements (the bodies' and the extrinsics' poses drawn by ``pose``); a body in
    ``one_instant`` is the one-instant fit's (no twist, stamps at its
    time), one in ``twist_prior`` has a prior on its twist. Returns (parts, ext)."""
    ext_cov = ext_cov or (lambda r: random_cov(r, (0.1, 0.5), (0.3e-3, 2e-3)))
    uncertain = [s for s, (u, _, _) in enumerate(SOURCES) if u]
    estimated = [s for s, (_, e, _) in enumerate(SOURCES) if e]
    E = np.array([pose(rng) for _ in uncertain])
    cov_e = np.array([ext_cov(rng) for _ in uncertain])
    shift = {s: dq.mul(E[j], dq.mul(lie.se3_exp(rng.multivariate_normal(np.zeros(6), cov_e[j])),
                                    dq.conj(E[j]))) for j, s in enumerate(uncertain)}
    out, slots = [], []
    for k in range(parts):
        X0 = pose(rng)
        V0 = rng.normal(size=6) * np.array([1, 1, 1, 0.3, 0.3, 0.3])
        src = rng.permutation(len(SOURCES))[:2 + k % 3]
        source = src[np.arange(per) % src.size]
        S = np.array([cov(rng) for _ in range(per)])
        if k in one_instant:
            Z = measure(rng, X0, S)
            model = static_model(per)
            V, ell, shared = np.zeros(6), np.zeros(0), None
        else:
            truth = np.array([SOURCES[s][2] for s in source])
            stamp = -rng.uniform(0.0, 0.1, per) + truth
            Z = measure(rng, dq.mul(X0, lie.se3_exp((stamp - truth)[:, None] * V0)), S)
            own = [s for s in dict.fromkeys(source.tolist()) if s in estimated]
            slot = np.array([own.index(s) if s in own else -1 for s in source])
            twist_w = (np.linalg.inv(np.diag([1, 1, 1, 0.3, 0.3, 0.3]) ** 2)
                       if k in twist_prior else None)
            model = Model(stamp, truth, slot,
                                  np.array([SOURCES[s][2] + 0.01 for s in own]),
                                  np.full(len(own), 1e4), True, twist_w)
            V = V0 + rng.normal(size=6) * 0.05
            ell = model.prior + rng.normal(size=len(own)) * 0.003
            shared = np.array([estimated.index(s) for s in own], np.intp)
        # a world-frame measurement of an uncertain source is off by its source's one error
        for i, s in enumerate(source):
            if s in shift:
                Z[i] = dq.mul(dq.conj(shift[s]), Z[i])
        inlier = np.ones(per, bool)
        if outliers:
            inlier[rng.integers(per)] = False
            Z[~inlier] = dq.mul(Z[~inlier], lie.se3_exp(np.array([0.3, 0, 0, 0.1, 0, 0])))
        slot_e = np.array([uncertain.index(s) if s in uncertain else -1 for s in source])
        start = dq.mul(X0, lie.se3_exp(rng.normal(size=6) * 0.02))
        out.append(Part(Z, S, model, inlier, slot_e, start, V, ell, shared))
        slots.append(slot_e)
    # the fit's latencies are those of the sources some body sees, in order of appearance
    seen = list(dict.fromkeys(np.concatenate([p.shared for p in out if p.shared is not None]
                                             + [np.zeros(0, np.intp)]).tolist()))
    out = [p if p.shared is None else p._replace(shared=np.array(
        [seen.index(j) for j in p.shared], np.intp)) for p in out]
    info = np.linalg.inv(cov_e)
    ext = Extrinsics(np.concatenate(slots), tuple(f"s{s}" for s in uncertain), E, cov_e,
                      0.5 * (info + np.swapaxes(info, 1, 2)))
    return out, ext


def rel(a, b):
    """|a - b| over |b|, both at their largest."""
    return np.abs(np.asarray(a) - b).max(initial=0.0) / max(np.abs(b).max(initial=0.0), 1e-300)


def assert_agrees(parts, ext, tol=1e-12, max_iter=100, bound=1e-10):
    a = ref.joint_fit(parts, ext, tol, max_iter)
    b = joint_fit(parts, ext, tol, max_iter, nis=True, jacobians=True)
    assert (b.status, b.iterations) == (a.status, a.iterations)
    assert b.offsets == a.offsets
    for k in range(len(parts)):
        assert np.abs(lie.se3_log(dq.mul(dq.conj(a.X[k]), b.X[k]))).max() < bound
        assert rel(b.V[k], a.V[k]) < bound or np.abs(b.V[k] - a.V[k]).max() < bound
        assert np.abs(b.ell[k] - a.ell[k]).max(initial=0.0) < bound
        assert np.abs(b.dt[k] - a.dt[k]).max() < bound
        assert np.abs(b.r[k] - a.r[k]).max() < bound * max(1.0, np.abs(a.r[k]).max())
        assert rel(b.G[k], a.G[k]) < bound
        nis, tested = ref.joint_nis(a, k, parts[k])
        assert np.array_equal(b.tested[k], tested)
        assert rel(b.nis[k], nis) < 1e2 * bound
        W = np.linalg.inv(parts[k].S)
        assert rel(b.cost[k], np.einsum("ni,nij,nj->n", a.r[k], W, a.r[k])) < 1e2 * bound
    assert np.abs(lie.se3_log(dq.mul(dq.conj(a.Ehat), b.Ehat))).max(initial=0.0) < bound
    # the information spans poses, twists (dt² smaller), latencies and extrinsics
    d = np.sqrt(np.diag(a.H))
    assert np.abs((b.H - a.H) / np.outer(d, d)).max() < bound
    assert np.array_equal(b.H, b.H.T) and np.array_equal(b.P, b.P.T)
    assert np.abs((b.P - a.P) * np.outer(d, d)).max() < bound
    assert np.abs((b.g - a.g) / d).max() < bound
    assert b.chi2 == pytest.approx(a.chi2, rel=bound)
    return a, b


@pytest.mark.parametrize("seed", range(8))
def test_agrees_with_the_reference_on_multi_part_problems(seed):
    """Several bodies sharing the extrinsics' errors and the estimated latencies, twist priors
    on some, an outlier each (in the fit's residuals, not its cost), one body of one instant."""
    rng = np.random.default_rng(900 + seed)
    parts, ext = problem(rng, parts=1 + seed % 4, per=6 + 3 * seed, outliers=seed % 2 == 1,
                         one_instant=(1,) if seed % 3 == 2 else (),
                         twist_prior=(0, 2) if seed % 2 == 0 else ())
    a, b = assert_agrees(parts, ext)
    dim = sum(p.model.offset for p in parts) + len(set(np.concatenate(
        [p.shared for p in parts if p.shared is not None]).tolist())) + 6 * len(ext.names)
    assert b.status == 0 and b.H.shape == (dim, dim)
    if seed % 2 == 1:
        assert all((~p.inlier).sum() == 1 for p in parts)
        assert all(n[~p.inlier][0] > 20 for n, p in zip(b.nis, parts))


def test_an_outlier_moves_nothing():
    """What inliers exclude changes only its own residual and NIS, not the fit."""
    rng = np.random.default_rng(930)
    parts, ext = problem(rng, parts=2, per=9, outliers=True)
    b = joint_fit(parts, ext, 1e-12, 100, nis=True)
    moved = [p._replace(Z=np.where(p.inlier[:, None], p.Z, random_pose(rng))) for p in parts]
    c = joint_fit(moved, ext, 1e-12, 100, nis=True)
    for k in range(2):
        assert np.array_equal(c.X[k], b.X[k]) and np.array_equal(c.V[k], b.V[k])
    assert np.array_equal(c.P, b.P) and c.chi2 == b.chi2
    assert np.array_equal(c.nis[0][parts[0].inlier], b.nis[0][parts[0].inlier])


def test_one_part_of_one_instant():
    rng = np.random.default_rng(931)
    parts, ext = problem(rng, parts=1, per=7, one_instant=(0,))
    a, b = assert_agrees(parts, ext)
    assert b.H.shape == (6 + 6 * len(ext.names),) * 2


def summed_nis(fit, parts, ext, k):
    """Part k's inliers' leave-one-out NIS as wᵀ (S + G Hj⁻¹ Gᵀ) w, w = S⁻¹ (r − G P g), with
    Hj the priors' information (the reference's normal equations with no inlier) and the other
    inliers' summed: the NIS the downdate computes, without its cancellation."""
    from dqpose.fusion.extrinsics import _layout
    lay = _layout(parts, ext)
    L = np.zeros(lay.prior.size)
    for m, ell in zip(lay.maps, fit.ell):
        L[m] = ell
    none = [ref.Prepared(*p._replace(inlier=np.zeros_like(p.inlier)), W=ref._inv(p.S),
                         A=ref._carried(p, ext)) for p in parts]
    prior = ref.joint_state(none, ext, lay, fit.X, fit.V, L, fit.Ehat)[3]
    own = [np.einsum("nji,njk,nkl->nil", G, ref._inv(p.S), G)[p.inlier]
           for G, p in zip(fit.G, parts)]
    others = prior + sum(o.sum(axis=0) for kk, o in enumerate(own) if kk != k)
    p, G, r = parts[k], fit.G[k], fit.r[k]
    nis = np.zeros(len(r))
    for j, i in enumerate(np.flatnonzero(p.inlier)):
        Hj = others + np.delete(own[k], j, axis=0).sum(axis=0)
        w = np.linalg.solve(p.S[i], r[i] - G[i] @ fit.P @ fit.g)
        nis[i] = w @ (p.S[i] + G[i] @ np.linalg.solve(Hj, G[i].T)) @ w
    return nis


def test_hard_case_near_pi_and_tiny_covariances():
    """Bodies and extrinsics turned by nearly π, two measurements ~89° either side of their
    body (residuals near a quarter turn, with covariances as wide), and a third of the others
    with covariances 1e-8 times the others': the two fits, run to the step limit (so that
    neither stops at a different step below tol), agree to rounding amplified by the
    information's conditioning (up to 4e14)."""
    rng = np.random.default_rng(932)

    def cov(r):
        return random_cov(r) * (1e-8 if r.random() < 0.3 else 1.0)
    for _ in range(6):
        parts, ext = problem(rng, parts=2, per=8, pose=near_pi, twist_prior=(0, 1), cov=cov)
        p = parts[0]
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        xi = np.zeros((p.Z.shape[0], 6))
        xi[:2, :3] = np.outer([1.0, -1.0], np.deg2rad(89.0) * axis)
        S = p.S.copy()
        S[:2] = [random_cov(rng, (30, 60), (0.05, 0.2)) for _ in range(2)]
        parts[0] = p._replace(Z=dq.mul(p.Z, lie.se3_exp(xi)), S=S)
        a = ref.joint_fit(parts, ext, 0.0, 15)
        b = joint_fit(parts, ext, 0.0, 15, nis=True, jacobians=True)
        sd = np.sqrt(np.diag(a.P))
        d = np.concatenate([np.r_[lie.se3_log(dq.mul(dq.conj(a.X[k]), b.X[k])), b.V[k] - a.V[k]]
                            for k in range(2)])
        # cond(H) reaches 4e14 here: Gauss-Newton's own steps stall at ~1e-8, where the two
        # fits' sums, in different orders, leave them
        assert np.abs(d / sd[:24]).max() < 1e-4
        scale = np.sqrt(np.diag(a.H))
        assert np.abs((b.H - a.H) / np.outer(scale, scale)).max() < 1e-5
        assert np.abs((b.P - a.P) / np.outer(sd, sd)).max() < 1e-5
        for k in range(2):
            nis, tested = ref.joint_nis(a, k, parts[k])
            assert np.array_equal(b.tested[k], tested)
            # a measurement 1e4 times surer than the rest: the reference's downdate
            # W - W G P Gᵀ W cancels to below P's own accuracy (~1e-6 here) and can turn
            # negative; the C fit sums the others' information instead, as summed_nis does
            trace = np.trace(parts[k].S, axis1=1, axis2=2)
            ordinary = trace > 1e-4 * np.median(trace)
            assert np.abs(b.nis[k] - nis)[ordinary].max() < 1e-4 * nis.max()
            summed = summed_nis(a, parts, ext, k)
            assert (summed[tested] > 0).all()
            assert np.abs(b.nis[k] - summed).max() < 1e-5 * summed.max()
        assert b.chi2 == pytest.approx(a.chi2, rel=1e-6)
        assert np.linalg.norm(b.r[0][:2, :3], axis=1).min() > 1.2


def test_arguments_named():
    rng = np.random.default_rng(933)
    parts, ext = problem(rng, parts=1, per=5)
    p = parts[0]
    good = dict(poses=p.Z, covariances=p.S, inliers=None, counts=np.array([5]),
                stamps=p.model.stamp, latencies=p.model.latency, latency_slots=p.model.slot,
                extrinsic_slots=p.slot, starts=p.start[None], twists=p.V[None],
                twist_flags=np.array([True]), twist_information=np.zeros((1, 6, 6)),
                twist_priors=np.array([False]), latency_starts=p.ell, priors=p.model.prior,
                prior_information=p.model.prior_w, extrinsics=ext.E,
                extrinsic_information=ext.info)

    k = p.model.prior.size

    def call(**change):
        return _c.joint_fit(*{**good, **change}.values())
    assert call()[14] == 0
    for name, value, text in [
        ("covariances", p.S[:4], r"^covariances: expected shape \(5, 6, 6\), got \(4, 6, 6\)"),
        ("counts", np.array([4]), r"^counts: they sum to 4, not the 5 poses"),
        ("counts", np.array([-1]), r"^counts\[0\]: -1 is negative"),
        ("starts", np.ones((1, 8)), r"^starts\[0\]: "),
        ("poses", np.where(np.arange(5)[:, None] == 3, np.nan, p.Z), r"^poses\[3\]: "),
        ("extrinsic_slots", np.array([0, 0, 9, 0, 0]),
         r"^extrinsic_slots\[2\]: 9 is not -1 or an index < 3"),
        ("latency_slots", np.full(5, k), rf"^latency_slots\[0\]: {k} is not -1 or an index < {k}"),
        ("covariances", np.where(np.arange(5)[:, None, None] == 1, -np.eye(6), p.S),
         r"^covariances\[1\]: not positive definite"),
        ("inliers", np.zeros(5, bool), r"^inliers: selects no measurement"),
        ("twist_information", np.full((1, 6, 6), np.inf),
         r"^twist_information\[0\]: contains NaN or infinity"),
        ("extrinsics", np.zeros((3, 6)), r"^extrinsics: expected shape \(m, 8\)"),
    ]:
        with pytest.raises(ValueError, match=text):
            call(**{name: value})
