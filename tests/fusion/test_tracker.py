"""dqpose.fusion.tracker: the per-body sliding window of a live stream."""
import dataclasses

import numpy as np
import pytest

from dqpose import dq, fusion, lie, limits
from dqpose.fusion import Measurement, Rows, Source, Tracker
from dqpose.fusion.bounds import TrackerBounds
from tests.fusion._moving import (
    ARM,
    ARM_RATE,
    CAM_A,
    CAM_B,
    CAMERA_RATE,
    SOURCES,
    WINDOW,
    error,
    sample,
    sizes,
    stream,
    trajectory,
)


def test_tracker_window_estimates_like_fuse_and_stays_bounded():
    rng = np.random.default_rng(72)
    T = trajectory(lie.se3_exp(rng.normal(size=6)), False)
    tracker = Tracker(WINDOW, sources=SOURCES)
    errors, sizes_seen = [], []
    for k, m in enumerate(stream(rng, T)):
        tracker.ingest([m], all_or_none=True)
        sizes_seen.append(len(tracker.measurements("box")))
        if k % 50 == 49:
            f = tracker.estimate("box")
            errors.append(sizes(error(f.mean, T(f.time)[0]))[1])
    assert max(sizes_seen) <= WINDOW * (ARM_RATE + 2 * CAMERA_RATE) + 4
    assert np.median(errors) < 1e-3
    window = tracker.measurements("box")
    f = tracker.estimate("box", time=0.98)
    g = fusion.fuse(np.array([m.pose for m in window]), np.array([m.covariance for m in window]),
                    names=[m.source for m in window], sources=SOURCES,
                    times=[m.time for m in window], time=0.98)
    assert np.array_equal(f.mean, g.mean) and np.array_equal(f.covariance, g.covariance)
    assert tracker.bodies == ("box",)


def test_framed_sources_fit_like_fuse_bit_for_bit_and_their_window_is_as_given():
    """The tracker keeps each row in the world frame once (extrinsic, body offset and the
    covariance the offset moves): its fit equals fuse's over the rows as given, and its window
    gives them back as they came (not in the world frame)."""
    rng = np.random.default_rng(5)
    T = trajectory(lie.se3_exp(rng.normal(size=6)), False)
    framed = [Source("cam_a", lie.se3_exp(rng.normal(size=6)), lie.se3_exp(0.3 * rng.normal(
                  size=6)), latency=SOURCES[0].latency),
              Source("cam_b", lie.se3_exp(rng.normal(size=6)), latency=SOURCES[1].latency)]
    tracker = Tracker(WINDOW, sources=framed)       # "arm" is not configured: the world frame
    given = list(stream(rng, T))[:120]
    tracker.ingest(given, all_or_none=True)
    window = tracker.measurements("box")
    kept = {(m.source, m.time) for m in window}
    for m in given:
        if (m.source, m.time) in kept:
            w = next(w for w in window if (w.source, w.time) == (m.source, m.time))
            # (the covariance as checked: its symmetric part)
            assert np.array_equal(w.pose, m.pose)
            assert np.array_equal(w.covariance, 0.5 * (m.covariance + m.covariance.T))
    for nis in (True, False):
        f = tracker.estimate(rows=tracker._rows("box"), nis=nis)
        g = fusion.fuse(np.array([m.pose for m in window]),
                        np.array([m.covariance for m in window]),
                        names=[m.source for m in window], sources=framed,
                        times=[m.time for m in window])
        assert np.array_equal(f.mean, g.mean) and np.array_equal(f.covariance, g.covariance)
        assert np.array_equal(f.residuals, g.residuals)


def test_tracker_time_going_back_beyond_the_window_is_an_error_naming_the_measurement():
    tracker = Tracker(WINDOW, sources=SOURCES)
    X = lie.se3_exp(np.full(6, 0.1))
    tracker.ingest([Measurement("arm", "box", 1.0, X), Measurement("arm", "box", 0.9, X)],
                   all_or_none=True)
    assert len(tracker.measurements("box")) == 2  # out of order within the window is fine
    late = Measurement("cam_a", "box", 0.83, X)  # taken at 0.79, 0.216 s before 1.006
    with pytest.raises(ValueError, match=r"^measurements\[1\] \(body 'box', source 'cam_a', "
                                         r"time 0.83\): taken at 0.7[89].* "
                                         r"beyond the window 0.2 s"):
        tracker.ingest([Measurement("arm", "box", 1.01, X), late], all_or_none=True)
    assert len(tracker.measurements("box")) == 2  # all or none
    # another body has its own clock
    tracker.ingest([Measurement("arm", "other", 0.0, X)], all_or_none=True)


def test_measurements_ingested_one_by_one_keep_the_good_and_name_the_others():
    """ingest of Measurement objects (not all or none): a row that is not one, and one whose pose
    has the wrong shape, are answered by index and kept out; the good rows are taken in."""
    tracker = Tracker(WINDOW, sources=SOURCES)
    X = lie.se3_exp(np.full(6, 0.1))
    errors = tracker.ingest([Measurement("arm", "box", 1.0, X), "not one",
                             Measurement("arm", "box", 1.01, X[:7]),
                             Measurement("arm", "box", 1.02, X)])
    assert [(k, str(e)) for k, e in errors] == [
        (1, "measurements[1]: expected a Measurement, got str"),
        (2, "measurements[2].pose: expected shape (8,), got (7,)")]
    assert tracker.window_of("box").times.tolist() == [1.0, 1.02]
    with pytest.raises(ValueError, match=r"^measurements\[1\]: expected a Measurement"):
        tracker.ingest([Measurement("arm", "box", 1.03, X), 5], all_or_none=True)
    assert tracker.count("box") == 2


def test_tracker_bodies_are_independent():
    rng = np.random.default_rng(73)
    Ta = trajectory(lie.se3_exp(rng.normal(size=6)), False)
    Tb = trajectory(lie.se3_exp(rng.normal(size=6)), True)
    a = stream(rng, Ta, body="a")
    b = stream(rng, Tb, body="b", end=1.3)
    both, alone = Tracker(WINDOW, sources=SOURCES), Tracker(WINDOW, sources=SOURCES)
    for m in sorted(a + b, key=lambda m: m.time):
        both.ingest([m], all_or_none=True)
    alone.ingest(a, all_or_none=True)
    assert set(both.bodies) == {"a", "b"}
    fa, ga = both.estimate("a"), alone.estimate("a")
    assert fa.time == ga.time and np.array_equal(fa.mean, ga.mean)
    assert np.array_equal(fa.covariance, ga.covariance)
    fb = both.estimate("b")
    assert fb.time > fa.time + 0.25
    assert sizes(error(fb.mean, Tb(fb.time)[0]))[1] < 3e-3
    both.remove("b")
    with pytest.raises(ValueError, match=r"^body: no measurements of 'b'"):
        both.estimate("b")


@pytest.mark.parametrize("measurement, message", [
    (Measurement("arm", "box", np.nan, np.eye(1, 8)[0]), r"^measurements\[0\]\.time: must be "
                                                          r"finite"),
    (Measurement("arm", "box", 0.0, np.ones(8)), r"^measurements\[0\]\.pose: "),
    (Measurement("arm", "", 0.0, np.eye(1, 8)[0]), r"^measurements\[0\]\.body: empty"),
    (Measurement("arm", "box", 0.0, np.eye(1, 8)[0], np.eye(3)),
     r"^measurements\[0\]\.covariance: expected shape \(6, 6\)"),
    (Measurement("arm", "box", 0.0, np.eye(1, 8)[0], -np.eye(6)),
     r"^measurements\[0\]\.covariance: not positive definite"),
    (Measurement("arm", "box", 0.0, np.eye(1, 8)[0], weight=0.0),
     r"^measurements\[0\]\.weight: must be positive"),
    (Measurement("arm", "box", 0.0, [[1, 0], [0]]),
     r"^measurements\[0\]\.pose: expected shape \(8,\), got a ragged sequence"),
    ("pose", r"^measurements\[0\]: expected a Measurement, got str"),
])
def test_tracker_bad_measurement_names_it(measurement, message):
    tracker = Tracker(WINDOW)
    with pytest.raises(ValueError, match=message):
        tracker.ingest([measurement], all_or_none=True)
    assert tracker.bodies == ()


def test_tracker_bad_options_fail_at_construction():
    with pytest.raises(ValueError, match=r"^window: must be positive"):
        Tracker(0.0)
    with pytest.raises(ValueError, match=r"^max_skew: must be nonnegative"):
        Tracker(0.2, max_skew=-1.0)
    with pytest.raises(ValueError, match=r"^acceleration_psd: not positive semidefinite"):
        Tracker(0.2, acceleration_psd=-np.eye(6))
    with pytest.raises(ValueError, match=r"^sources\[0\]\.name: empty"):
        Tracker(0.2, sources=[Source("")])


def _two_trackers_and_a_batch(seed: int):
    """Two trackers fed the same stream of body "box" but its last 10 measurements, and those
    10 as arrays ``(batch, poses, covs, times, names, bodies)`` (copies, to spoil)."""
    rng = np.random.default_rng(seed)
    T = trajectory(lie.se3_exp(rng.normal(size=6)), False)
    ms = stream(rng, T, end=0.3)
    a, b = Tracker(WINDOW, sources=SOURCES), Tracker(WINDOW, sources=SOURCES)
    head, batch = ms[:-10], ms[-10:]
    a.ingest(head, all_or_none=True)
    b.ingest(head, all_or_none=True)
    return a, b, (batch, np.array([m.pose for m in batch]),
                  np.array([m.covariance for m in batch]), np.array([m.time for m in batch]),
                  [m.source for m in batch], ["box"] * 10)


def test_tracker_ingest_keeps_the_valid_measurements_and_names_the_others():
    tracker, alone, (batch, poses, covs, times, names, bodies) = _two_trackers_and_a_batch(74)
    poses[1, 0] = np.nan
    covs[4, 1, 1] = -1.0
    times[6] = np.inf
    times[8] -= 0.5
    bodies[9] = ""
    errors = tracker.ingest(Rows(bodies, names, times, poses, covs), ids=np.arange(100, 110))
    assert [k for k, _ in errors] == [1, 4, 6, 8, 9]
    text = [str(e) for _, e in errors]
    assert text[0] == "measurements[1].pose: contains NaN or infinity"
    assert text[1] == "measurements[4].covariance: not positive definite"
    assert text[2] == "measurements[6].time: must be finite, got inf"
    assert text[3].startswith("measurements[8] (body 'box'") and "beyond the window" in text[3]
    assert text[4] == "measurements[9].body: empty (every measurement names its body)"
    good = [0, 2, 3, 5, 7]
    alone.ingest([batch[k] for k in good], all_or_none=True)
    w = tracker.window_of("box")
    assert w.ids[-5:].tolist() == [100 + k for k in good]
    f, g = tracker.estimate("box"), alone.estimate("box")
    assert np.array_equal(f.mean, g.mean) and np.array_equal(f.covariance, g.covariance)


def test_rows_a_decoder_checked_answer_as_ingest_does():
    """``ingest``'s ``checked`` (StreamFuse's and World.Publish's rows, checked in C): the rows
    coded bad are named by the tracker's own check, the others taken in unchecked, a row too old
    for the window refused still; the same errors, window and estimate as :meth:`Tracker.ingest`."""
    a, b, (batch, poses, covs, times, names, bodies) = _two_trackers_and_a_batch(76)
    poses[1, 0] = np.nan
    covs[4, 1, 1] = -1.0
    times[8] -= 0.5                         # a good row, too old for the window
    bodies[9] = ""
    codes = np.zeros(10, np.int64)
    codes[[1, 4, 9]] = 7                    # what the decoder refused
    ids = np.arange(100, 110)
    want = a.ingest(Rows(bodies, names, times, poses, covs), ids=ids)
    got = b.ingest(Rows(bodies, names, times, poses, covs), ids=ids, checked=codes)
    assert [k for k, _ in got] == [1, 4, 8, 9]
    assert [(k, type(e), str(e)) for k, e in got] == [(k, type(e), str(e)) for k, e in want]
    assert a.window_of("box").ids.tolist() == b.window_of("box").ids.tolist()
    f, g = a.estimate("box"), b.estimate("box")
    assert f.mean.tobytes() == g.mean.tobytes() and f.nis.tobytes() == g.nis.tobytes()
    c, _, (_, poses, covs, times, names, bodies) = _two_trackers_and_a_batch(76)
    # every row good: none checked again
    assert c.ingest(Rows(bodies, names, times, poses, covs), ids=ids,
                    checked=np.zeros(10, np.int64)) == []
    assert c.window_of("box").ids[-10:].tolist() == ids.tolist()


def test_one_instant_at_its_time_is_the_static_fusion_bit_for_bit():
    rng = np.random.default_rng(75)
    X = lie.se3_exp(rng.normal(size=6))
    S = np.array([CAM_A, CAM_B, ARM, ARM])
    Z = np.concatenate([sample(rng, lambda t: X[None], C, np.zeros(1)) for C in S])
    Z[3] = dq.mul(Z[3], lie.se3_exp(np.array([0, 2.5, 0, 0.2, 0, 0])))   # a flipped one
    names = ["cam_a", "cam_b", "arm", "arm"]
    for robust in (False, True):
        static = fusion.fuse(Z, S, names=names, robust=robust)
        f = fusion.fuse(Z, S, names=names, robust=robust, times=[1.5] * 4, time=1.5,
                        max_skew=0.01, sources=[Source("arm", latency_sigma=0.01)])
        assert np.array_equal(f.mean, static.mean)
        assert np.array_equal(f.covariance, static.covariance)
        assert np.array_equal(f.nis, static.nis) and f.rejected == static.rejected
        assert f.time == 1.5 and f.dropped == () and f.twist is None
        assert f.latencies == (fusion.Latency("arm", 0.0, 0.01, 0.0, 0.01),)
    prior = np.diag([0.5 ** 2] * 3 + [0.2 ** 2] * 3)
    f = fusion.fuse(Z[:3], S[:3], times=[1.5] * 3, twist_covariance=prior)
    assert np.array_equal(f.mean, fusion.fuse(Z[:3], S[:3]).mean)
    assert np.array_equal(f.twist, np.zeros(6)) and np.array_equal(f.twist_covariance, prior)


def test_rows_checked_in_c_answer_as_numpy_does_each_row():
    """The tracker's row checks run in one C pass (``check_rows``) and only the rows it cannot
    pass are checked in NumPy: good rows mixed with every kind of bad one, and covariances at
    the edge of positive definite, get the verdicts, messages and symmetrised covariances of
    NumPy's checks of each row alone (``_poses``, ``_covariances``)."""
    from dqpose.errors import rename
    from dqpose.fusion import validation
    from tests.fusion._scenes import random_cov
    rng = np.random.default_rng(31)
    n = 48
    Z = np.array([lie.se3_exp(rng.normal(size=6)) for _ in range(n)])
    S = np.array([random_cov(rng) for _ in range(n)])
    Z[1, 2] = np.nan
    Z[2] *= 1.1                                            # not unit
    Z[3, 4:] += 0.1 * Z[3, :4]                             # not a rigid motion
    S[4, 0, 1] = np.inf
    S[5, 0, 1] += 1e-6 * S[5].max()                        # asymmetric
    S[6] -= 1.01 * S[6].max() * np.eye(6)                  # not positive definite
    S[7, 2, 2] = 1e-30                                     # variance out of range
    S[8, 0, 1] += 1e-12 * S[8].max()                       # asymmetric within tolerance
    for k, low in enumerate([0.0, 1e-17, -1e-17, 1e-16, -1e-16, 1e-15, 1e-9, -1e-9, 1e-6], 9):
        Q = np.linalg.qr(rng.normal(size=(6, 6)))[0]       # at the edge of positive definite
        S[k] = (Q * np.r_[np.ones(5), low]) @ Q.T * 1e-4
    bodies, sources = [f"b{k % 3}" for k in range(n)], ["cam"] * n
    ok, errors, covs = validation.check_rows(bodies, sources, np.zeros(n), Z, S)
    for k in range(n):
        try:
            validation.checked_poses(Z[k:k + 1])
            want = validation.checked_covariances(S[k:k + 1], None, 1)[0]
        except ValueError as e:
            assert not ok[k], k
            assert str(errors[k]) == str(rename(e, {
                "poses": f"measurements[{k}].pose",
                "covariances": f"measurements[{k}].covariance"})), k
            continue
        assert ok[k] and k not in errors, k
        assert covs[k].tobytes() == want.tobytes(), k
    assert ok[:9].tolist() == [True] + [False] * 7 + [True] and ok[9:].sum() >= 2


def _jumpy(max_rows=100_000) -> Tracker:
    bounds = TrackerBounds.of(limits.Limits(max_time_jump=2.0, max_time=50.0))
    return Tracker(10.0, sources=[Source("cam", latency=0.5)],
                   bounds=dataclasses.replace(bounds, max_rows=max_rows))


def _fed(t: Tracker, times, origin=None, body="box") -> list[str]:
    n = len(times)
    return [f"{k}: {e}" for k, e in t.ingest(Rows([body] * n, ["cam"] * n, np.array(times, float),
                                                   np.tile([1.0, 0, 0, 0, 0, 0, 0, 0], (n, 1)),
                                                   np.tile(np.eye(6), (n, 1, 1))), origin=origin)]


def test_a_jump_waits_for_a_second_measurement_from_whoever_may_confirm_it():
    """The jump rule (service/csrc/store.c dq_store_ingest): a row taken more than max_time_jump
    after its body's newest (earlier rows of the call counted) is refused without moving the
    body, its text naming how far; the next one near it confirms it, from another origin, or
    from the same one only while no other origin fed the body within the limit."""
    t = _jumpy()
    assert _fed(t, [1.0, 2.0], "a") == []
    assert t.newest("box") == 1.5                       # stamp less the source's latency
    one = _fed(t, [6.0], "a")
    assert one == ["0: measurements[0]: body 'box', source 'cam', time 6.0: taken 4 s after "
                   "the newest measurement of the body, so not used (a second measurement near "
                   "it would confirm the jump), over the server's limit max_time_jump = 2 s "
                   "(dqpose serve --max-time-jump)"] and t.newest("box") == 1.5
    assert _fed(t, [6.5], "a") == [] and t.newest("box") == 6.0     # a's own: alone, confirmed
    assert _fed(t, [6.6], "b") == []                    # b feeds the body now
    said = _fed(t, [12.0], "a")                         # a's jump, b fed lately
    assert said and "near it from another producer would confirm" in said[0]
    assert _fed(t, [12.1], "a") and t.newest("box") == 6.1          # a cannot confirm it
    assert _fed(t, [12.2], "b") == [] and t.newest("box") == 11.7   # b can
    # in one call: the earlier rows count, for the jump and for the window floor
    assert _fed(t, [13.0, 15.0, 14.9], "b") == [] and t.newest("box") == 14.5
    # a body new to the stream: its earliest row of the call is the reference
    assert [e[:2] for e in _fed(t, [1.0, 1.5, 9.0], "a", "new")] == ["2:"]
    # a stream's rows (no origin) confirm their own jumps
    s = _jumpy()
    assert _fed(s, [1.0]) == [] and _fed(s, [9.0]) and _fed(s, [9.1]) == []
    assert s.newest("box") == 8.6


def test_times_beyond_max_time_and_past_the_stream_room_are_refused_by_name():
    t = _jumpy(max_rows=4)
    assert _fed(t, [60.0, 1.0]) == ["0: measurements[0].time: 60 s is beyond +-50 s, over the "
                                    "server's limit max_time = 50 s (dqpose serve --max-time)"]
    assert _fed(t, [1.1, 1.2, 1.3, 1.4]) == [
        "3: measurements[3]: the stream's windows hold 1 measurements, over the server's limit "
        "max_stream_measurements = 4 measurements (dqpose serve --max-stream-measurements)"]
    assert t.count("box") == 4


@pytest.mark.parametrize("bodies", [1, 60])
def test_spans_are_each_bodys_own_looks(bodies):
    """Tracker.spans (ListFrames' spans, rates and sources of many bodies in one C pass) gives
    what oldest, newest, rows_ending and by_source give body by body, with measurements late,
    out of order and past a cap."""
    rng = np.random.default_rng(bodies)
    t = Tracker(2.0, bounds=TrackerBounds.of(limits.DEFAULT), robust=False)
    names = [f"b{k}" for k in range(60)]
    for step in range(40):
        n = 30
        t.ingest(Rows([names[k] for k in rng.integers(0, 60, n)],
                      [f"cam{k}" for k in rng.integers(0, 5, n)],
                      step * 0.1 + rng.uniform(-0.5, 0.1, n), np.tile(dq.identity(), (n, 1)),
                      np.tile(np.eye(6) * 1e-4, (n, 1, 1))))
    asked = list(t.bodies)[:bodies]
    oldest, newest, near, fed = t.spans(asked, 1.0)
    for k, b in enumerate(asked):
        assert oldest[k] == t.oldest(b) and newest[k] == t.newest(b)
        assert near[k] == len(t.rows_ending(b, t.newest(b), 1.0))
        assert fed[k] == tuple(t.by_source(b))
