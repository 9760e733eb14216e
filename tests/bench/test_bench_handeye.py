"""The hand-eye benchmark: OpenCV's conventions as the bench feeds and reads them (exact data gives
every method's truth back), the judge of bad answers, and a small run whose table has every method
on every row and says what issue 11 claims of ours.

The OpenCV rows need the benchmark's OpenCV 4.x environment (created from PyPI on first use, in
tests/bench/_build/opencv4); without network those tests are skipped with the reason."""
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from dqpose import dq, lie
from tests import _handeye
from tests.bench import bench_handeye as bench
from tests.bench import handeye_opencv

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def opencv4():
    try:
        return bench.opencv4_python()[0]
    except bench.OpenCVUnavailable as e:
        pytest.skip(str(e))


@pytest.mark.parametrize("setup", _handeye.SETUPS)
@pytest.mark.parametrize("geometry", _handeye.GEOMETRIES)
def test_opencv_conventions_on_exact_data(opencv4, setup, geometry):
    """Noise-free scenes: each of the seven methods returns the true X (and Shah/Li the true Z)
    once the bench has put the poses into OpenCV's conventions and read the answers back."""
    scenes = [_handeye.scene(10, setup, geometry, (0.0, 0.0), None, seed=s) for s in range(3)]
    B = np.stack([sc.base_flange for sc in scenes])
    A = np.stack([sc.camera_target for sc in scenes])
    solved = bench.opencv_solve(opencv4, B, A, setup)
    assert set(solved) == set(bench.OPENCV)
    for label, (X, Z, seconds, errors) in solved.items():
        assert (Z is not None) == (label in bench.OPENCV[len(bench.OPENCV_HAND_EYE):]), label
        assert not any(errors) and np.all(seconds > 0), label
        for k, sc in enumerate(scenes):
            for M, truth in ((X[k], sc.x), (None if Z is None else Z[k], sc.z)):
                if M is None:
                    continue
                got, why = bench.judge(M, truth)
                assert why == "", (label, why)
                err = lie.se3_log(dq.mul(dq.inv(got), truth))
                assert np.abs(err).max() < 1e-8, (label, setup, geometry, err)
    # and a wrong reading is not accepted by accident: the other setup's inputs miss by far
    other = "eye_to_hand" if setup == "eye_in_hand" else "eye_in_hand"
    X = bench.opencv_solve(opencv4, B, A, other)["OpenCV Tsai"][0]
    got = [bench.judge(M, sc.x)[0] for M, sc in zip(X, scenes)]
    assert all(g is None or _handeye.pose_error(g, sc.x)[0] > 1.0 for g, sc in zip(got, scenes))


def test_opencv_environment_offline_says_so(tmp_path, monkeypatch):
    """No package index: a clear error naming the environment and the way around it, not a
    traceback from pip."""
    monkeypatch.setattr(handeye_opencv, "OPENCV_ENV", tmp_path / "opencv4")
    monkeypatch.setenv("PIP_INDEX_URL", "http://127.0.0.1:9/simple")   # nothing listens there
    monkeypatch.setenv("PIP_FIND_LINKS", "")
    with pytest.raises(bench.OpenCVUnavailable) as e:
        bench.opencv4_python()
    msg = str(e.value)
    assert str(tmp_path / "opencv4") in msg and "offline" in msg
    assert "--opencv-python" in msg and "--no-opencv" in msg
    with pytest.raises(bench.OpenCVUnavailable, match="--opencv-python"):
        bench.opencv4_python(str(tmp_path / "no-such-python"))


def test_judge_names_bad_answers():
    truth = _handeye.pose([0.3, -0.2, 0.1], [0.05, 0.02, 0.1])
    M = dq.to_matrix(truth)
    X, why = bench.judge(M, truth)
    assert why == "" and _handeye.pose_error(X, truth) == pytest.approx((0.0, 0.0), abs=1e-9)
    nan = M.copy()
    nan[0, 3] = np.nan
    flip = M.copy()
    flip[:3, 2] *= -1
    skew = M.copy()
    skew[:3, :3] *= 1.01
    for bad, reason in ((nan, "NaN"), (flip, "reflection"), (skew, "not a rotation"),
                        (np.eye(4), "identity")):
        assert bench.judge(bad, truth) == (None, reason)
    # the identity is only wrong when the truth is not the identity
    assert bench.judge(np.eye(4), dq.from_matrix(np.eye(4)))[1] == ""
    # a rigid inverse of the 4x4 keeps what it was given (NaN stays NaN, R transposed)
    inv = bench._inverse_matrix(np.stack([M, nan]))
    assert np.allclose(inv[0] @ M, np.eye(4)) and np.isnan(inv[1]).any()


def test_bad_answers_count_as_infinite_errors():
    s = bench.Series()
    truth = _handeye.pose([0.1, 0.0, 0.0], [0.0, 0.0, 0.1])
    s.add(truth, truth, 0.001)
    s.add(None, truth, 0.001, bad="NaN")
    s.add(None, truth, 0.001, bad="identity")
    assert np.median(s.rot) == np.inf and s.bad == ["NaN", "identity"]
    assert "2/3 (NaN, identity)" in bench.render({"scene": {"m": s}})


def _rows(stdout, header):
    """The rows of the Markdown table whose first column is ``header``."""
    for block in stdout.split("\n\n"):
        lines = [ln for ln in block.splitlines() if ln.startswith("|")]
        if lines and lines[0].startswith(f"| {header} "):
            return [[c.strip() for c in ln.strip("|").split("|")] for ln in lines[2:]]
    raise AssertionError(f"no table headed {header!r} in:\n{stdout}")


def _table(stdout):
    rows = _rows(stdout, "scene")
    out = {}
    for scene, method, rot, trans, nees, seconds, bad in rows:
        out.setdefault(scene, {})[method] = dict(rot=float(rot), trans=float(trans), nees=nees,
                                                 seconds=seconds, bad=bad)
    return out


def test_bench_small_run(opencv4):
    """A small run in CI: every method on every row, ours never bad, with a NEES; the broken-data
    table has every kind and ours flags each; the targets are stated."""
    out = subprocess.run([sys.executable, "-m", "tests.bench.bench_handeye", "--trials", "3",
                          "--poses", "20", "--charuco-trials", "1", "--broken-trials", "1"],
                         cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    table = _table(out.stdout)
    cases = bench.cases(poses=(20,))
    assert len(table) == len(cases) + 1                     # the synthetic rows and ChArUco
    for case in cases:
        assert case.label in table
    have_ours = bench.have_ours()
    for scene, res in table.items():
        assert set(bench.OPENCV) <= set(res), scene
        for m, r in res.items():
            if m in bench.OPENCV:
                assert r["nees"] == "—"
            else:   # ours, in every variant: an answer every time, with its NEES
                assert r["bad"].startswith(("0/3", "0/1")), (scene, m, r)
                assert float(r["nees"]) > 0
        if have_ours:
            assert bench.OURS in res, scene
    assert "Issue 11 targets:" in out.stdout
    broken = _rows(out.stdout, "broken data")
    assert [r[0] for r in broken] == [k.replace("_", " ") for k in _handeye.BROKEN]
    for r in broken:   # every OpenCV column filled: an answer, or what went wrong
        assert all(c != "—" for c in r[2:]), r
        if have_ours:
            assert "SILENT" not in r[1] and ("refused" in r[1] or "warned" in r[1]), r


def _best_opencv(res):
    return (min(np.median(res[m].rot) for m in bench.OPENCV),
            min(np.median(res[m].trans) for m in bench.OPENCV))


@pytest.mark.parametrize("geometry", _handeye.GEOMETRIES)
def test_ours_beats_opencv_on_the_issues_rows(opencv4, geometry):
    """20 poses, 0.1°/0.5 mm, 40 seeded trials: ours at least matches the best OpenCV method in
    rotation (within 10 %: they are within a few % at 200 trials) and beats it in translation
    on the wrist geometry; on OpenCV's own geometry it is several times better in both."""
    if not bench.have_ours():
        pytest.skip("dqpose.handeye not there yet")
    res = bench.run_case(bench.Case(geometry, 20, (0.1, 0.5), None), 40, 1, opencv4)
    rot, trans = np.median(res[bench.OURS].rot), np.median(res[bench.OURS].trans)
    best_rot, best_trans = _best_opencv(res)
    if geometry == "wrist":
        assert rot <= 1.1 * best_rot and trans <= best_trans, (rot, trans, best_rot, best_trans)
    else:
        assert rot <= 0.5 * best_rot and trans <= 0.5 * best_trans, (rot, trans, best_rot,
                                                                     best_trans)
    assert not res[bench.OURS].bad


def test_ours_beats_opencv_end_to_end(opencv4):
    """Rendered ChArUco views, detected: ours given the detector's covariances beats every OpenCV
    method on the same detections."""
    if not bench.have_ours():
        pytest.skip("dqpose.handeye not there yet")
    res, rejected = bench.run_charuco(3, 1, opencv4)
    assert bench.OURS_COVARIANCE in res
    best_rot, best_trans = _best_opencv(res)
    s = res[bench.OURS_COVARIANCE]
    assert np.median(s.rot) < best_rot and np.median(s.trans) < best_trans
