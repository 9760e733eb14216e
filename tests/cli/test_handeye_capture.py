"""`dqpose handeye capture` as a user runs it (a subprocess, on the UR simulator and the rendered
camera): an interrupted capture is continued with --resume or replaced with --force, and the
capture's first view is one the detector measures as its covariance says (not head-on)."""
from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

pytest.importorskip("rtde_control")
pytest.importorskip("cv2")

from dqpose import dq, fusion, lie
from tests.cli._interrupt import ROOT, Command

NEES_BOUND = fusion.chi2_quantile(0.999, 6)


def _dqpose(*argv, timeout: float = 600.0):
    return subprocess.run([sys.executable, "-m", "dqpose.cli", *argv], cwd=ROOT,
                          capture_output=True, text=True, timeout=timeout)


def _poses(folder) -> list[dict]:
    with open(os.path.join(folder, "poses.json")) as f:
        return json.load(f)["poses"]


def _pose(doc) -> np.ndarray:
    return dq.from_pose([doc["orientation"][c] for c in "wxyz"],
                        [doc["position"][c] for c in "xyz"])


def _views(folder) -> list[str]:
    return sorted(n for n in os.listdir(folder) if n.startswith("view_"))


@pytest.fixture(scope="module")
def interrupted(tmp_path_factory):
    """A capture of 8 views interrupted by one Ctrl-C once three views were taken."""
    folder = str(tmp_path_factory.mktemp("resume") / "calib")
    cmd = Command("handeye", "capture", folder, "--views", "8")
    try:
        cmd.wait_for(lambda: "view 3:" in cmd.stderr, "three views taken")
        cmd.interrupt()
        code = cmd.wait()
    finally:
        cmd.kill()
    return folder, code, cmd.stderr


def test_an_interrupted_capture_says_how_to_go_on_and_keeps_its_views(interrupted):
    folder, code, err = interrupted
    assert code == 130, err
    assert "interrupted" in err and f"dqpose handeye capture {folder} --resume" in err, err
    taken = _poses(folder)
    assert len(taken) >= 3 and _views(folder)[:len(taken)] == [p["image"] for p in taken]
    # the plain rerun does not overwrite it, and says what would
    again = _dqpose("handeye", "capture", folder, "--views", "8")
    assert again.returncode == 2
    assert "already holds a capture" in again.stderr and "--resume" in again.stderr \
        and "--force" in again.stderr, again.stderr
    assert _poses(folder) == taken


def test_resume_completes_the_interrupted_capture_and_it_solves(interrupted, tmp_path):
    folder = str(tmp_path / "calib")
    shutil.copytree(interrupted[0], folder)
    before = _poses(folder)
    r = _dqpose("handeye", "capture", folder, "--resume", "--views", "8")
    assert r.returncode == 0, r.stderr
    assert f"resuming: {len(before)} views" in r.stderr
    after = _poses(folder)
    assert len(after) == 8
    assert [p["image"] for p in after[:len(before)]] == [p["image"] for p in before]
    np.testing.assert_allclose([_pose(p["base_to_flange"]) for p in after[:len(before)]],
                               [_pose(p["base_to_flange"]) for p in before], atol=1e-12)
    assert _views(folder) == [f"view_{i:03d}.png" for i in range(8)]
    # the new views were moved to, not the old ones taken again
    flanges = np.array([_pose(p["base_to_flange"]) for p in after])
    for i in range(len(before), 8):
        for j in range(i):
            angle = 2 * math.acos(min(1.0, abs(float(flanges[i, :4] @ flanges[j, :4]))))
            assert angle > math.radians(3), (i, j)
    s = _dqpose("handeye", "solve", folder, "--local")
    assert s.returncode == 0, s.stderr
    with open(os.path.join(folder, "truth.json")) as f:
        truth = json.load(f)
    with open(os.path.join(folder, "handeye.json")) as f:
        got = json.load(f)
    for key in ("x", "z"):
        xi = lie.se3_log(dq.mul(dq.inv(_pose(got[key])), _pose(truth[key])))
        cov = np.array(got[f"covariance_{key}"]).reshape(6, 6)
        assert float(xi @ np.linalg.solve(cov, xi)) < NEES_BOUND


def test_force_starts_over(interrupted, tmp_path):
    folder = str(tmp_path / "calib")
    shutil.copytree(interrupted[0], folder)
    with open(os.path.join(folder, "handeye.json"), "w") as f:
        f.write("{}")                                   # an earlier solve's output
    with open(os.path.join(folder, "notes.txt"), "w") as f:
        f.write("mine")                                  # not the capture's: kept
    old = _poses(folder)
    r = _dqpose("handeye", "capture", folder, "--force", "--views", "4", "--seed", "5")
    assert r.returncode == 0, r.stderr
    assert "--force: removed the previous capture's" in r.stderr
    new = _poses(folder)
    assert len(new) == 4 and _views(folder) == [f"view_{i:03d}.png" for i in range(4)]
    assert new[1:] != old[1:4]
    assert not os.path.exists(os.path.join(folder, "handeye.json"))
    assert os.path.isfile(os.path.join(folder, "notes.txt"))


def test_resume_and_force_are_one_or_the_other(tmp_path):
    r = _dqpose("handeye", "capture", str(tmp_path / "x"), "--resume", "--force")
    assert r.returncode == 2 and "not allowed with" in r.stderr


def test_the_first_view_is_measured_as_its_covariance_says(interrupted):
    """View 0 is where the capture starts. Head-on to the board the rendered corners' detection
    was off along the view by 0.26-0.38 mm (NEES ~25 against its own covariance, noise or not),
    so the solver left view 0 out of every capture; the start view is tilted as every other
    view is."""
    from dqpose import handeye
    from dqpose.cli.handeye import read_truth
    from dqpose.drivers.camera import CharucoCamera, load_board, load_intrinsics, read_image
    folder = interrupted[0]
    x, z = read_truth(folder, "eye_in_hand")
    cam = CharucoCamera(load_intrinsics(os.path.join(folder, "intrinsics.json")),
                        load_board(os.path.join(folder, "board.json")))
    flange = _pose(_poses(folder)[0]["base_to_flange"])
    true = handeye.view_at(flange, x, z, "eye_in_hand")          # T_camera_board
    axis = dq.to_matrix(true)[:3, 2]                             # the board's normal, camera frame
    assert math.degrees(math.acos(abs(axis[2]))) > 10            # not head-on
    d = cam.detect(read_image(os.path.join(folder, _poses(folder)[0]["image"])))
    xi = lie.se3_log(dq.mul(dq.inv(d.pose), true))
    assert float(xi @ np.linalg.solve(d.covariance, xi)) < NEES_BOUND
