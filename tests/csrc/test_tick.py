"""A tick's answer in one C call (service/csrc/tick.c, ``World.tick_wire``) against the Python
path it stands for (``World.tick`` + ``fused_pose_bytes``): the same FusedPose bytes over scenes
it makes (moving bodies, sources with latencies, estimated latencies, a twist prior, max_skew
drops, capped windows, several sources, a body offset, ticks between measurements, uncertain
extrinsics: the joint fit, one instant: the static fit), and None, leaving the answer to Python,
where it does not (robust, an acceleration_psd, a tick beyond max_extrapolation)."""
import numpy as np
import pytest

from dqpose import dq, lie
from dqpose.fusion import Measurement, Source
from dqpose.fusion.chi2 import chi2_quantile
from dqpose.fusion.consistency import verdict_bounds
from dqpose.rpc.world_convert import body_pose_bytes
from dqpose.world import BodyPose, OutOfRange, World, WorldBounds, WorldOptions
from tests.fusion._scenes import random_cov, random_pose

V = np.array([0.3, -0.2, 0.1, 0.2, 0.05, -0.1])
#: an uncertain mount: 1 degree and 5 mm
MOUNT = np.diag(np.r_[np.full(3, np.deg2rad(1.0)), np.full(3, 5e-3)] ** 2)


def world_of(rng, sources, options, times, bodies=("box", "cup"), per_body=None, jitter=0.0):
    """A world fed by every source measuring every body at ``times`` (each source's stamps
    shifted by its latency, plus ``jitter``), the bodies moving with twist V."""
    w = World(sources=sources, options=options, bounds=WorldBounds(
        max_measurements_per_body=per_body or WorldBounds().max_measurements_per_body))
    X0 = {b: random_pose(rng, 0.5) for b in bodies}
    ms = []
    for t in times:
        for s in sources:
            for b in bodies:
                c = random_cov(rng)
                truth = dq.mul(X0[b], lie.se3_exp(t * V))
                z = dq.mul(truth, lie.se3_exp(rng.multivariate_normal(np.zeros(6), c)))
                if s.extrinsic is not None:
                    z = dq.mul(dq.conj(s.extrinsic), z)
                ms.append(Measurement(s.name, b, float(t + s.latency + jitter * rng.random()),
                                      z, c))
    assert not w.publish(ms).errors
    return w


def python_bytes(w: World, body: str, t, request: int) -> bytes:
    p, ids = w.tick(body, t)
    return body_pose_bytes(p, request, ids.tolist())


def ticks_of(w: World, body: str, times):
    """Each tick's C bytes and the Python path's."""
    return [(w.tick_wire(body, t, 5), python_bytes(w, body, t, 5)) for t in times]


SCENES = {
    "moving, one source": ([Source("cam")], {}),
    "moving, several sources with latencies": (
        [Source("cam", random_pose(np.random.default_rng(1)), latency=0.02),
         Source("arm", latency=0.005), Source("imu")], {}),
    "an estimated latency": ([Source("cam", latency=0.03, latency_sigma=0.01), Source("arm")],
                             {}),
    "two estimated latencies": ([Source("cam", latency=0.03, latency_sigma=0.01),
                                 Source("arm", latency=0.01, latency_sigma=0.02)], {}),
    "a twist prior": ([Source("cam"), Source("arm")],
                      {"twist_covariance": np.diag([0.1, 0.1, 0.1, 0.01, 0.01, 0.01])}),
    "max_skew drops": ([Source("cam", latency=0.01), Source("arm")], {"max_skew": 0.08}),
    "no max_extrapolation": ([Source("cam")], {"max_extrapolation": None}),
    "an unconfigured source": ([Source("cam")], {}),
    "an uncertain extrinsic (the joint fit)": (
        [Source("cam", random_pose(np.random.default_rng(2)), extrinsic_covariance=MOUNT)], {}),
    "two uncertain extrinsics and an exact source": (
        [Source("cam", random_pose(np.random.default_rng(2)), extrinsic_covariance=MOUNT),
         Source("top", extrinsic_covariance=MOUNT * 4), Source("arm", latency=0.01)], {}),
    "an uncertain extrinsic, an estimated latency, a twist prior, max_skew": (
        [Source("cam", random_pose(np.random.default_rng(2)), extrinsic_covariance=MOUNT,
                latency=0.02, latency_sigma=0.01), Source("arm")],
        {"twist_covariance": np.eye(6) * 0.05, "max_skew": 0.08}),
    "a body offset (covariances moved into the world frame)": (
        [Source("cam", random_pose(np.random.default_rng(4)),
                body_offset=random_pose(np.random.default_rng(5), 0.1)), Source("arm")], {}),
}


@pytest.mark.parametrize("case", list(SCENES))
def test_the_c_tick_writes_the_python_paths_bytes(case):
    sources, kw = SCENES[case]
    rng = np.random.default_rng(len(case))
    w = world_of(rng, sources, WorldOptions(window=0.3, buffer=2.0, **kw),
                 np.arange(40) * 0.021, jitter=0.004)
    if case == "an unconfigured source":      # a source the world was not told about
        assert not w.publish([Measurement("phone", "box", 0.85, random_pose(rng),
                                          random_cov(rng))]).errors
    made = 0
    for body in ("box", "cup"):
        newest = w.newest(body)
        for c, py in ticks_of(w, body, [None, newest, newest - 0.013, newest + 0.02,
                                        newest - 0.15]):
            assert c == py
            made += 1
    assert made == 10
    if case == "max_skew drops":
        f = w.tick("box", w.newest("box") - 0.15)[0].fused
        assert f is not None and f.dropped       # the C wrote them: the bytes are equal


def test_a_capped_window_fits_its_last_rows():
    rng = np.random.default_rng(3)
    w = world_of(rng, [Source("cam"), Source("arm", latency=0.01)],
                 WorldOptions(window=0.5, buffer=1.0), np.arange(30) * 0.02, per_body=12)
    assert w.tracker.capped("box", 0.5)
    for c, py in ticks_of(w, "box", [None, w.newest("box")]):
        assert c is not None and c == py


def test_the_verdicts_bounds_are_chi2s():
    b = verdict_bounds(0.99, 40)
    assert b.shape[1] > 40
    for count in (1, 7, 40):
        assert b[0, count] == chi2_quantile(0.005, 6 * count) / count
        assert b[1, count] == chi2_quantile(0.995, 6 * count) / count


INSTANT = {
    "plain": ([Source("cam"), Source("arm"), Source("imu")], {}),
    "a twist prior": ([Source("cam"), Source("arm")], {"twist_covariance": np.eye(6) * 0.01}),
    "an estimated latency": ([Source("cam", latency=0.02, latency_sigma=0.01), Source("arm")],
                             {}),
    "one measurement": ([Source("cam")], {}),
    "an uncertain extrinsic (the static joint fit)": (
        [Source("cam", random_pose(np.random.default_rng(2)), extrinsic_covariance=MOUNT),
         Source("arm")], {}),
    "an uncertain extrinsic, an estimated latency, a twist prior": (
        [Source("cam", random_pose(np.random.default_rng(2)), extrinsic_covariance=MOUNT,
                latency=0.01, latency_sigma=0.005), Source("top", extrinsic_covariance=MOUNT)],
        {"twist_covariance": np.eye(6) * 0.01}),
    # the kept rows one instant: the static fit of every row, none listed as dropped (Python's)
    "max_skew drops": ([Source("cam"), Source("arm")], {"max_skew": 0.1}),
}


@pytest.mark.parametrize("case", list(INSTANT))
def test_one_instant_is_the_static_fit_in_c_too(case):
    sources, kw = INSTANT[case]
    rng = np.random.default_rng(len(case) + 100)
    w = world_of(rng, sources, WorldOptions(window=0.3, buffer=2.0, **kw), [0.5], ("box",))
    if case == "max_skew drops":
        assert not w.publish([Measurement("cam", "box", 0.3, random_pose(rng),
                                          random_cov(rng))]).errors
    (c, py), = ticks_of(w, "box", [None])
    assert c is not None and c == py
    f = w.tick("box", None)[0].fused
    assert f is not None and f.twist is None if "twist" not in case else f.twist is not None


LEFT = {
    "robust": ([Source("cam")], {"robust": True}, np.arange(20) * 0.02),
    "an acceleration_psd": ([Source("cam")], {"acceleration_psd": np.eye(6) * 0.1},
                            np.arange(20) * 0.02),
}


@pytest.mark.parametrize("case", list(LEFT))
def test_what_the_c_tick_leaves_to_python(case):
    sources, kw, times = LEFT[case]
    w = world_of(np.random.default_rng(7), sources, WorldOptions(window=0.3, buffer=2.0, **kw),
                 times)
    assert w.tick_wire("box", None, 1) is None
    python_bytes(w, "box", None, 1)          # the Python path answers it


def test_a_tick_beyond_max_extrapolation_is_the_python_paths_error():
    w = world_of(np.random.default_rng(8), [Source("cam")],
                 WorldOptions(window=0.3, buffer=2.0), np.arange(40) * 0.02)
    newest = w.newest("box")
    # past the newest: refused by the row pick, which both paths share
    with pytest.raises(OutOfRange) as python:
        w.tick("box", newest + 0.2)
    with pytest.raises(OutOfRange) as c:
        w.tick_wire("box", newest + 0.2, 1)
    assert str(c.value) == str(python.value)
    # 0.15 s before the window's oldest row: the fit's refusal, named by the Python path
    t = newest - 0.45
    assert w.tick_wire("box", t, 1) is None
    with pytest.raises(OutOfRange, match="beyond max_extrapolation"):
        w.tick("box", t)


def test_the_bindings_refusals_name_the_argument():
    from dqpose import _dqcore
    w = world_of(np.random.default_rng(9), [Source("cam")], WorldOptions(window=0.3),
                 np.arange(10) * 0.02)
    t = w.tracker
    s, rows = t.store, w._tick_rows("box", None)
    w.tick_wire("box", None, 1)
    opts, bounds = w._wire._options, verdict_bounds(t.options.probability, 40)
    args = [opts, s.wposes, s.covs, s.times, s.codes, s.ids, rows, np.nan, "box", 1, bounds]
    for k, bad, name in ((6, np.array([s.n + len(s.ids)]), "rows"),
                         (1, s.wposes[:, :7], "poses"), (10, bounds[:1], "bounds")):
        with pytest.raises(ValueError, match=name):
            _dqcore.tick(*args[:k], bad, *args[k + 1:])
    assert _dqcore.tick(*args) == python_bytes(w, "box", None, 1)


@pytest.mark.parametrize("shared", [False, True])
def test_an_answer_relative_to_another_body_is_the_python_paths(shared):
    """The pose and covariance World.relative gives at the fit's time, the fit's other fields:
    two worlds of the same measurements, one answered in C, the other by the Python path (a
    Lookup's warm start depends on the Lookups made before, so each world makes the same)."""
    sources = [Source("cam", random_pose(np.random.default_rng(2)),
                      extrinsic_covariance=MOUNT if shared else None), Source("arm")]
    worlds = [world_of(np.random.default_rng(12), sources, WorldOptions(window=0.3, buffer=2.0),
                       np.arange(40) * 0.021, jitter=0.004) for _ in range(2)]
    c, py = worlds
    for t in (None, c.newest("box"), c.newest("box") - 0.05):
        got = c.tick_wire("box", t, 3, "cup")
        p, ids = py.tick("box", t)
        rel = py.relative("cup", "box", p.time)
        assert got is not None and got == body_pose_bytes(
            BodyPose("box", rel.time, rel.pose, rel.covariance, p.fused), 3, ids.tolist())
    # a body the world does not hold: the Python path names it (after the fit)
    assert c.tick_wire("box", None, 3, "nothing") is None
