"""`dqpose smooth` as a user runs it (a subprocess; on a real server through the shipped client,
and --local): it says that the ends are held at rest and how far they lie from the recording,
`--free-ends` keeps the recording's motion there, and the plot draws the recording and the
smoothed path from one origin."""
from __future__ import annotations

import io
import math
import os
import subprocess
import sys

import numpy as np
import pytest

from dqpose import dq
from tests.cli._cli import server  # noqa: F401 (a fixture)

pytest.importorskip("casadi")

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
LIMIT_FLAGS = ["--max-linear-velocity", "0.5", "--max-angular-velocity", "2",
               "--max-linear-acceleration", "2", "--max-angular-acceleration", "4"]
SPEED, TURN = 0.1, 0.3            # m/s along x, rad/s about z: moving at the first sample


def _recording(path, n: int = 151, rate: float = 100.0):
    """A tool moving at constant speed and turning at a constant rate from the first sample to
    the last (no noise): the smoothing's optimum with free ends is the recording itself."""
    t = np.arange(n) / rate
    half = 0.5 * TURN * t
    q = np.stack([np.cos(half), 0 * t, 0 * t, np.sin(half)], axis=1)
    p = np.stack([0.4 + SPEED * t, 0 * t, 0.3 + 0 * t], axis=1)
    with open(path, "w") as f:
        f.write("t,x,y,z,qw,qx,qy,qz\n")
        for row in np.concatenate([t[:, None], p, q], axis=1):
            f.write(",".join(repr(float(v)) for v in row) + "\n")
    return t, dq.from_pose(q, p)


def _dqpose(*argv, timeout: float = 300.0):
    return subprocess.run([sys.executable, "-m", "dqpose.cli", *argv], cwd=ROOT,
                          capture_output=True, text=True, timeout=timeout)


def _samples(text: str):
    a = np.loadtxt(io.StringIO(text), delimiter=",", skiprows=1)
    return a[:, 0], dq.from_pose(a[:, 4:8], a[:, 1:4])


def _offset_mm(a, b) -> float:
    return 1e3 * float(np.linalg.norm(dq.to_pose(a)[1] - dq.to_pose(b)[1]))


@pytest.mark.parametrize("where", ["local", "server"])
def test_smooth_says_the_ends_are_held_at_rest_and_free_ends_follows_the_data(tmp_path, server,
                                                                              where):
    path = tmp_path / "moving.csv"
    t, truth = _recording(path)
    extra = ["--local"] if where == "local" else ["--server", server.target]

    rest = _dqpose("smooth", str(path), *LIMIT_FLAGS, *extra)
    assert rest.returncode == 0, rest.stderr
    _, out = _samples(rest.stdout)
    off = _offset_mm(out[0], truth[0])
    assert off > 2.0                     # held at rest while the recording moves at 0.1 m/s
    assert "ends held at rest" in rest.stderr and "--free-ends" in rest.stderr, rest.stderr
    # the figure it prints is the one measured on its output
    assert f"first pose {off:.2f} mm" in rest.stderr, rest.stderr

    free = _dqpose("smooth", str(path), "--free-ends", *LIMIT_FLAGS, *extra)
    assert free.returncode == 0, free.stderr
    times, out = _samples(free.stdout)
    np.testing.assert_allclose(times, t, atol=1e-9)
    for k in (0, -1):
        assert _offset_mm(out[k], truth[k]) < 0.05
        qa, qb = dq.to_pose(out[k])[0], dq.to_pose(truth[k])[0]
        assert 2 * math.acos(min(1.0, abs(float(qa @ qb)))) < 1e-4
    assert "ends free (--free-ends)" in free.stderr, free.stderr


def test_free_ends_through_the_client_and_the_domain_agree(server):
    from dqpose import smoothing, trajectory
    from dqpose.rpc.client import Client

    n = 80
    t = np.arange(n) / 100.0
    rng = np.random.default_rng(3)
    p = np.stack([0.4 + SPEED * t, 0.01 * np.sin(3 * t), 0.3 + 0 * t], axis=1)
    p += rng.normal(scale=3e-4, size=p.shape)
    poses = dq.from_pose(np.tile([1.0, 0, 0, 0], (n, 1)), p)
    limits = trajectory.Limits(0.5, 2.0, 2.0, 4.0)
    with Client(server.target) as c:
        got_t, got = c.smooth(t, poses, limits, free_ends=True)
    want_t, want = smoothing.smooth(t, poses, limits, free_ends=True)
    np.testing.assert_allclose(got_t, want_t, atol=1e-12)
    np.testing.assert_allclose(got, want, atol=1e-9)
    _, rest = smoothing.smooth(t, poses, limits)
    assert _offset_mm(rest[0], want[0]) > 1.0         # the field reached the solver


def test_free_ends_must_be_a_bool():
    from dqpose import smoothing, trajectory
    t = np.arange(5) / 10
    poses = dq.from_pose(np.tile([1.0, 0, 0, 0], (5, 1)), np.zeros((5, 3)))
    with pytest.raises(ValueError, match="free_ends"):
        smoothing.smooth(t, poses, trajectory.Limits(0.5, 2.0, 2.0, 4.0), free_ends="yes")


def test_the_plot_draws_the_recording_and_the_smoothed_path_from_one_origin(tmp_path):
    pytest.importorskip("matplotlib")
    from dqpose import smoothing, trajectory
    from dqpose.cli.plots import motion_figure

    path = tmp_path / "moving.csv"
    t, truth = _recording(path)
    limits = trajectory.Limits(0.5, 2.0, 2.0, 4.0)
    times, out = smoothing.smooth(t, truth, limits)        # ends at rest: off the recording
    fig = motion_figure(times, out, limits, raw=(t, truth))
    axis = fig.axes[1]                                     # orientation, top right
    smoothed_z = axis.lines[2].get_ydata()                 # x, y, z of the smoothed path
    raw_z = axis.lines[5].get_ydata()                      # then the recording's
    # In the middle the smoothed path lies on the recording (noise-free, slow), so the two
    # curves must meet there; drawn each from its own start they were apart by the smoothed
    # start's turn from the recording's (about 1.7 deg here).
    mid = len(t) // 2
    np.testing.assert_allclose(smoothed_z[mid], raw_z[mid], atol=2e-4)
    assert abs(raw_z[0]) < 1e-12 and abs(smoothed_z[0]) > 5e-3
    # position: drawn as it is, both
    np.testing.assert_allclose(fig.axes[0].lines[3].get_ydata(), dq.to_pose(truth)[1][:, 0])


def test_smooth_plot_says_the_ends_are_at_rest(tmp_path):
    pytest.importorskip("matplotlib")
    path = tmp_path / "moving.csv"
    _recording(path)
    png = tmp_path / "smooth.png"
    r = _dqpose("smooth", str(path), "--local", "--plot", str(png), *LIMIT_FLAGS)
    assert r.returncode == 0, r.stderr
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "ends held at rest" in r.stderr
