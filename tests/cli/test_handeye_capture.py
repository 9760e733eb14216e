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
    code = cmd.interrupted_when(lambda: "view 3:" in cmd.stderr, "three views taken")
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


def test_a_recorded_capture_holds_its_views_solves_and_residuals(tmp_path):
    pytest.importorskip("foxglove", reason="the [record] extra")
    from dqpose.cli.handeye_folder import read_truth
    from dqpose.record import handeye as views_of
    from dqpose.record.reader import read
    from dqpose.record.schemas import message_class
    from tests.record.test_recorder import messages

    folder, path = str(tmp_path / "calib"), str(tmp_path / "capture.mcap")
    res = _dqpose("handeye", "capture", folder, "--views", "6", "--record", path)
    assert res.returncode == 0, res.stderr
    assert f"recording: {path}" in res.stderr
    by_topic: dict = {}
    for topic, name, _, schema, data, _ in messages(path):    # every CRC checked
        by_topic.setdefault(topic, []).append((name, schema, data))
    rpc = "dqpose.v1.HandEye/Calibrate"
    requests, answers = (by_topic[f"/dqpose/{rpc}/{k}"] for k in ("requests", "answers"))
    assert 1 <= len(requests) == len(answers) <= 6 - 3    # a solve from the fourth view on
    Request = message_class(requests[-1][1], requests[-1][0])
    Answer = message_class(answers[-1][1], answers[-1][0])
    last, solved = Request.FromString(requests[-1][2]), Answer.FromString(answers[-1][2])
    # the last solve has every view, at the flange poses the capture saved
    flanges = [_pose(d["base_to_flange"]) for d in _poses(folder)]
    assert len(last.pairs) == len(flanges) == 6
    for p, f in zip(last.pairs, flanges):
        t = p.base_to_flange.position
        assert np.linalg.norm(dq.to_pose(f)[1] - [t.x, t.y, t.z]) < 1e-6
    x_true, _ = read_truth(folder, "eye_in_hand")
    x_pos = [solved.x.position.x, solved.x.position.y, solved.x.position.z]
    assert np.linalg.norm(dq.to_pose(x_true)[1] - x_pos) < 5e-3
    # the views: X and Z on /tf with their ellipsoids, the per-view residuals
    tf = message_class(by_topic["/tf"][-1][1], "foxglove.FrameTransforms")
    children = {t.child_frame_id for _, _, d in by_topic["/tf"]
                for t in tf.FromString(d).transforms}
    assert set(views_of.TF) <= children
    scene = message_class(by_topic[views_of.ELLIPSOIDS_TOPIC][-1][1], "foxglove.SceneUpdate")
    ents = scene.FromString(by_topic[views_of.ELLIPSOIDS_TOPIC][-1][2]).entities
    assert [e.frame_id for e in ents] == ["handeye/x", "handeye/z"]
    assert all(e.spheres[0].size.x > 0 for e in ents)
    rows = [json.loads(d) for _, _, d in by_topic[views_of.RESIDUALS_TOPIC]]
    last_rows = rows[-6:]
    assert [r["view"] for r in last_rows] == list(range(6))
    assert [r["translation"] for r in last_rows] == list(
        np.asarray(solved.residuals).reshape(-1, 2)[:, 1])
    targets = message_class(by_topic[views_of.TARGETS_TOPIC][-1][1], "foxglove.PosesInFrame")
    assert len(targets.FromString(by_topic[views_of.TARGETS_TOPIC][-1][2]).poses) == 6
    assert read(path).calls    # dqpose's own reader reads it too
