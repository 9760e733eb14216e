"""dqpose.riders: a source riding on a body (eye-in-hand: a camera on an arm's tool), composed
with its parent's fit when a fit takes its rows, in process, NumPy only."""
from __future__ import annotations

import numpy as np
import pytest

from dqpose import dq, lie
from dqpose.errors import Infeasible, WorldError
from dqpose.frames import Static
from dqpose.fusion import Source
from dqpose.limits import ANSWER_ROWS
from dqpose.world import Measurement, World, WorldOptions

X = lie.se3_exp(np.array([0.1, -0.2, 0.3, 0.02, 0.05, 0.08]))     # T_tool_camera
BOX = lie.se3_exp(np.array([0.0, 0.1, 0.0, 0.5, 0.2, 0.1]))       # T_world_box
T0 = lie.se3_exp(np.array([0.2, 0.0, 0.1, 0.3, 0.0, 0.2]))        # the tool at t = 10
V = np.array([0.3, -0.2, 0.4, 0.05, 0.03, -0.04])                 # its twist (body frame)
COV_ARM = np.diag([1e-8] * 3 + [1e-8] * 3)
COV_X = np.diag([4e-6] * 3 + [1e-6] * 3)
COV_CAM = np.diag([2.5e-5] * 3 + [4e-6] * 3)
RATE, N = 30.0, 10
_IDENT = np.array([1.0, 0, 0, 0, 0, 0, 0, 0])


def tool_at(t: float) -> np.ndarray:
    """The tool's known path: a constant twist (the fit's own motion model)."""
    return dq.mul(T0, lie.se3_exp(V * (t - 10.0)))


def draw(rng, cov):
    return lie.se3_exp(rng.multivariate_normal(np.zeros(6), cov)) if rng is not None \
        else np.array([1.0, 0, 0, 0, 0, 0, 0, 0])


def scene(rng=None, n: int = N, x_true=X):
    """The arm's measurements of the tool and the camera's of the box at the same instants."""
    out = []
    for k in range(n):
        t = 10.0 + k / RATE
        tool = tool_at(t)
        cam = dq.conj(dq.mul(tool, x_true))
        out.append(Measurement("arm", "tool", t, dq.mul(tool, draw(rng, COV_ARM)), COV_ARM))
        out.append(Measurement("cam", "box", t, dq.mul(dq.mul(cam, BOX), draw(rng, COV_CAM)),
                               COV_CAM))
    return out


def world(**options) -> World:
    return World(sources=[Source("arm"),
                          Source("cam", extrinsic=X, extrinsic_covariance=COV_X, parent="tool")],
                 options=WorldOptions(**{"window": 0.5, "buffer": 5.0, **options}))


def error(est: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """The right perturbation taking ``est`` to ``truth``."""
    return lie.se3_log(dq.mul(dq.conj(est), truth))


def test_without_noise_the_box_is_the_composition():
    w = world()
    assert w.publish(scene()).accepted == 2 * N
    for p in (w.pose("box"), w.relative("", "box")):
        np.testing.assert_allclose(p.pose * np.sign(p.pose[0]), BOX, rtol=0, atol=1e-9)
    # in the tool's frame, the box is the camera's composition with the extrinsic
    t = 10.0 + (N - 1) / RATE
    rel = w.relative("tool", "box", t)
    want = dq.mul(dq.conj(tool_at(t)), BOX)
    np.testing.assert_allclose(rel.pose * np.sign(rel.pose[0] * want[0]), want, rtol=0,
                               atol=1e-9)


def mean_nees(seed: int, trials: int, trial) -> float:
    """The mean NEES of ``trial(rng, x_true) -> (answer, truth)`` over ``trials``, each with the
    camera's true extrinsic ``X·Exp(ε)`` drawn first (one generator seeded ``seed``)."""
    rng = np.random.default_rng(seed)
    nees = []
    for _ in range(trials):
        p, truth = trial(rng, dq.mul(X, draw(rng, COV_X)))
        e = error(p.pose, truth)
        nees.append(e @ np.linalg.solve(p.covariance, e))
    return float(np.mean(nees))


def box_nees(seed: int = 39, trials: int = 200) -> float:
    """The box's mean NEES over ``trials``: each draws the true extrinsic ``X·Exp(ε)`` and the
    noises, the box's fused world pose against the truth under its covariance."""
    def trial(rng, x_true):
        w = world()
        w.publish(scene(rng, x_true=x_true))
        return w.pose("box"), BOX
    return mean_nees(seed, trials, trial)


def test_eye_in_hand_box_nees_over_200_trials():
    nees = box_nees()
    assert abs(nees - 6.0) <= 0.7, nees


def test_a_camera_on_a_static_mount_of_the_tool_and_on_a_static_of_the_world():
    # the mount fixed on the tool (uncertain), the camera on the mount: X = M · X_mount
    M = lie.se3_exp(np.array([0.0, 0.1, 0.0, 0.0, 0.02, 0.03]))
    mount = Static("tool", "mount", M, COV_X)
    w = World(sources=[Source("arm"), Source("cam", extrinsic=dq.mul(dq.conj(M), X),
                                             extrinsic_covariance=COV_X, parent="mount")],
              options=WorldOptions(window=0.5, buffer=5.0))
    w.configure(sources=w.sources, arms={}, options=w.options, statics=[mount])
    w.publish(scene())
    p = w.pose("box")
    np.testing.assert_allclose(p.pose * np.sign(p.pose[0]), BOX, rtol=0, atol=1e-9)
    assert w.horizon("box") == w.horizon("tool")      # it waits for the arm
    # a camera on a static fixed in the world sees the box as a world-fixed camera does
    C = dq.mul(tool_at(10.0), X)
    w = World(sources=[Source("cam", extrinsic=_IDENT, parent="stand")],
              options=WorldOptions(window=0.5, buffer=5.0))
    w.configure(sources=w.sources, arms={}, options=w.options,
                statics=[Static("", "stand", C, None)])
    w.publish([Measurement("cam", "box", 10.0 + k / RATE, dq.mul(dq.conj(C), BOX), COV_CAM)
               for k in range(N)])
    p = w.pose("box")
    np.testing.assert_allclose(p.pose * np.sign(p.pose[0]), BOX, rtol=0, atol=1e-9)
    assert np.linalg.eigvalsh(p.covariance).max() < COV_CAM.max()


CUP = lie.se3_exp(np.array([0.2, 0.0, -0.1, 0.45, 0.3, 0.05]))   # T_world_cup


def box_cup_nees(seed: int = 8, trials: int = 200) -> float:
    """The Lookup of the cup in the box's frame (both fixed, seen by the camera on the tool)
    over ``trials``: its mean NEES, the shared extrinsic's and tool's errors cancelling."""
    def trial(rng, x_true):
        ms = scene(rng, x_true=x_true)
        for m in ms[1::2]:     # the cup in the same images
            cam = dq.conj(dq.mul(tool_at(m.time), x_true))
            ms.append(Measurement("cam", "cup", m.time, dq.mul(dq.mul(cam, CUP),
                                                                draw(rng, COV_CAM)), COV_CAM))
        w = world()
        w.publish(ms)
        return w.relative("box", "cup"), dq.mul(dq.conj(BOX), CUP)
    return mean_nees(seed, trials, trial)


def test_two_bodies_seen_by_the_camera_on_the_tool_share_its_errors():
    nees = box_cup_nees()
    assert abs(nees - 6.0) <= 0.7, nees


def test_a_row_its_parent_is_not_known_at_is_dropped_with_the_reason():
    w = world()
    w.publish(scene())
    late = 10.0 + (N - 1) / RATE + 0.25      # the tool known up to 0.25 s before
    cam = dq.conj(dq.mul(tool_at(late), X))
    w.publish([Measurement("cam", "box", late, dq.mul(cam, BOX), COV_CAM)])
    p, ids = w.tick("box", None)
    assert p.fused is not None and len(p.fused.dropped) == 1
    d = p.fused.dropped[0]
    assert d.index == len(ids) - 1 and ids[d.index] == 0    # after the rows fitted, its number
    assert d.source == "cam"
    assert d.reason.startswith(f"measurement {d.index} (cam): its parent 'tool' is not known "
                               f"at 10.55 ('tool' is known from "), d.reason
    np.testing.assert_allclose(p.pose * np.sign(p.pose[0]), BOX, rtol=0, atol=1e-9)


def test_a_tick_of_the_box_waits_for_the_tools_sources():
    w = world(max_delay=0.2)
    ms = scene()
    w.publish([m for m in ms if m.body == "box" or m.time <= 10.1])
    # the box's own camera is at 10.3; the arm, whose tool the camera rides on, at 10.1
    assert w.horizon("box") == pytest.approx(10.1)
    w.publish([m for m in ms if m.body == "tool" and m.time > 10.1])
    assert w.horizon("box") == pytest.approx(10.0 + (N - 1) / RATE)


def test_bodies_without_riders_keep_the_c_tick():
    w = world()
    w.publish(scene())
    w.publish([Measurement("arm", "cup", 10.2, BOX, COV_ARM),
               Measurement("arm", "cup", 10.25, BOX, COV_ARM)])
    assert w.tick_wire("cup", None, 0) is not None
    assert w.tick_wire("box", None, 0) is None       # composed in Python
    assert w.tick_wire("tool", None, 0, relative_to="box") is None


def test_a_ticks_cost_counts_the_parents_fits():
    w = world()
    w.publish(scene())
    tool, box = w.tick_window("tool"), w.tick_window("box")
    assert tool.rows == N
    # each of the box's rows costs the tool's fit at its time besides itself
    assert box.rows == N + N * (N + ANSWER_ROWS)


def test_the_box_follows_the_tools_new_measurements():
    w = world()
    ms = scene()
    w.publish(ms)
    before = w.pose("box", 10.2)
    # the tool measured elsewhere from now on (its fit moves): the box's answer is made again
    shift = lie.se3_exp(np.array([0, 0, 0, 0.01, 0, 0]))
    w.publish([Measurement("arm", "tool", m.time + 0.005, dq.mul(shift, m.pose), COV_ARM)
               for m in ms if m.body == "tool"])
    after = w.pose("box", 10.2)
    assert np.abs(after.pose - before.pose).max() > 1e-3


def test_an_arm_whose_source_rides_on_a_body_is_refused():
    with pytest.raises(WorldError) as e:
        World(sources=[Source("ur", parent="base")], arms={"ur": "ur"})
    assert isinstance(e.value, Infeasible)
    assert str(e.value).startswith("arms['ur']: source 'ur' rides on 'base'")



def test_a_rider_beside_an_acceleration_psd_is_refused():
    with pytest.raises(WorldError) as e:
        world(acceleration_psd=np.eye(6) * 1e-3)
    assert not isinstance(e.value, Infeasible)
    assert str(e.value).startswith("sources[1].parent: source 'cam' rides on 'tool': its rows "
                                   "carry their parent's covariance"), str(e.value)


if __name__ == "__main__":      # the figures docs/benchmarks/world.md quotes
    import argparse
    ap = argparse.ArgumentParser(description="the box's mean NEES over 200 trials a seed")
    ap.add_argument("--speed", type=float, default=1.0, help="the tool's twist times this")
    ap.add_argument("--arm-variance", type=float, default=COV_ARM[0, 0],
                    help="the arm's measurement variance (rad², m²)")
    args = ap.parse_args()
    V, COV_ARM = V * args.speed, np.eye(6) * args.arm_variance
    for seed in (39, 1, 2, 3):
        print(f"seed {seed}: mean NEES {box_nees(seed):.2f} over 200 trials (6 expected), the cup "
              f"in the box's frame {box_cup_nees(seed):.2f}; the tool turning "
              f"{np.linalg.norm(V[:3]):.2f} rad/s, the arm's variance {COV_ARM[0, 0]:g}")
