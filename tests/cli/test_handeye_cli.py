"""`dqpose handeye capture` and `dqpose handeye solve` on the simulators: the UR simulator driven
through the real ur_rtde, the board rendered by the simulated camera and detected by
drivers.camera, solved on a real server on 127.0.0.1 or --local; the answer checked against the
simulation's truth with the covariance it comes with."""
from __future__ import annotations

import json
import os
import shutil

import numpy as np
import pytest

pytest.importorskip("rtde_control")
pytest.importorskip("cv2")

from dqpose import dq, fusion, lie
from tests.cli._cli import run, server  # noqa: F401

# NEES of a 6-dof estimate: below this in 99.9 % of the runs when the covariance is honest
NEES_BOUND = fusion.chi2_quantile(0.999, 6)


def _pose(doc) -> np.ndarray:
    return dq.from_pose([doc["orientation"][c] for c in "wxyz"],
                        [doc["position"][c] for c in "xyz"])


def _capture(tmp_path_factory, setup: str, views: int) -> str:
    folder = str(tmp_path_factory.mktemp(setup) / "capture")
    from dqpose.cli import main
    assert main(["handeye", "capture", folder, "--setup", setup, "--views", str(views)]) == 0
    return folder


@pytest.fixture(scope="module")
def eye_in_hand(tmp_path_factory):
    return _capture(tmp_path_factory, "eye_in_hand", 8)


def _check_against_truth(folder: str, result: str):
    """The solved X and Z are within what their covariances allow of the simulation's truth."""
    with open(os.path.join(folder, "truth.json")) as f:
        truth = json.load(f)
    with open(result) as f:
        got = json.load(f)
    assert got["setup"] == truth["setup"]
    for key in ("x", "z"):
        est, true = _pose(got[key]), _pose(truth[key])
        cov = np.array(got[f"covariance_{key}"]).reshape(6, 6)
        xi = lie.se3_log(dq.mul(dq.inv(est), true))         # true = est * Exp(xi)
        nees = float(xi @ np.linalg.solve(cov, xi))
        assert nees < NEES_BOUND, (key, nees, xi)
        # and the covariance is a calibration's, not a shrug: well under a millimetre
        assert np.sqrt(np.diag(cov))[3:].max() < 5e-4, cov


def test_capture_writes_what_solve_reads(eye_in_hand):
    names = sorted(os.listdir(eye_in_hand))
    assert names == ["board.json", "intrinsics.json", "poses.json", "truth.json"] + \
        [f"view_{i:03d}.png" for i in range(8)]
    with open(os.path.join(eye_in_hand, "poses.json")) as f:
        doc = json.load(f)
    assert doc["setup"] == "eye_in_hand" and len(doc["poses"]) == 8
    # the views were chosen to turn about different axes: no two alike
    flanges = np.array([_pose(p["base_to_flange"]) for p in doc["poses"]])
    for i in range(8):
        for j in range(i):
            angle = 2 * np.arccos(min(1.0, abs(float(flanges[i, :4] @ flanges[j, :4]))))
            assert angle > np.radians(3), (i, j)


def test_solve_on_the_server_recovers_the_truth(eye_in_hand, server, capsys, tmp_path):
    out = {k: str(tmp_path / n) for k, n in (("report", "r.txt"), ("plot", "p.png"),
                                             ("json", "r.json"))}
    code, stdout, err = run(capsys, "handeye", "solve", eye_in_hand, "--server", server.target,
                            "--report", out["report"], "--plot", out["plot"], "-o", out["json"])
    assert code == 0, err
    _check_against_truth(eye_in_hand, out["json"])
    with open(out["report"]) as f:
        assert f.read() == stdout
    assert "X = T_flange_camera" in stdout and "Z = T_base_target" in stdout
    for i in range(8):                    # a line per view, by its image
        assert f"view_{i:03d}.png" in stdout
    assert "against the simulation's truth: X off by" in stdout
    with open(out["plot"], "rb") as f:
        assert f.read(8) == b"\x89PNG\r\n\x1a\n"


def test_corner_level_on_the_server(eye_in_hand, server, capsys, tmp_path):
    result = str(tmp_path / "r.json")
    code, stdout, err = run(capsys, "handeye", "solve", eye_in_hand, "--server", server.target,
                            "--corners", "--refine-focal", "-o", result,
                            "--report", str(tmp_path / "r.txt"), "--plot", str(tmp_path / "p.png"))
    assert code == 0, err
    assert "corner level: reprojection RMS per view" in stdout and "focal lengths x" in stdout
    _check_against_truth(eye_in_hand, result)
    code, _, err = run(capsys, "handeye", "solve", eye_in_hand, "--local", "--refine-focal")
    assert code == 2 and "--refine-focal: needs --corners" in err


def test_solve_local_reads_ur_rotation_vectors_in_millimetres(eye_in_hand, capsys, tmp_path):
    from dqpose.drivers.rotvec import rotvec_from_pose
    folder = str(tmp_path / "ur")
    shutil.copytree(eye_in_hand, folder)
    with open(os.path.join(folder, "poses.json")) as f:
        doc = json.load(f)
    os.remove(os.path.join(folder, "poses.json"))
    with open(os.path.join(folder, "poses.csv"), "w") as f:   # what a UR script would log
        for p in doc["poses"]:
            x, y, z, rx, ry, rz = rotvec_from_pose(_pose(p["base_to_flange"])).tolist()
            f.write(f"{p['image']},{1e3 * x!r},{1e3 * y!r},{1e3 * z!r},{rx!r},{ry!r},{rz!r}\n")
    code, stdout, err = run(capsys, "handeye", "solve", folder, "--local")
    assert code == 0, err
    assert "note: positions read as millimetres" in stdout
    assert "note: rotations read as UR rotation vectors" in stdout
    assert "note: setup: eye_in_hand (the default" in stdout
    _check_against_truth(folder, os.path.join(folder, "handeye.json"))
    assert os.path.isfile(os.path.join(folder, "handeye.png"))
    assert os.path.isfile(os.path.join(folder, "handeye_report.txt"))


def test_eye_to_hand_capture_and_local_solve(tmp_path_factory, capsys):
    folder = _capture(tmp_path_factory, "eye_to_hand", 7)
    capsys.readouterr()
    code, stdout, err = run(capsys, "handeye", "solve", folder, "--local", "--estimate-noise")
    assert code == 0, err
    assert "X = T_base_camera" in stdout and "noise estimated from the residuals" in stdout
    _check_against_truth(folder, os.path.join(folder, "handeye.json"))


def test_unusable_views_are_refused_naming_the_images(eye_in_hand, server, capsys, tmp_path):
    folder = str(tmp_path / "few")
    shutil.copytree(eye_in_hand, folder)
    with open(os.path.join(folder, "poses.json")) as f:
        doc = json.load(f)
    doc["poses"] = doc["poses"][:2]
    with open(os.path.join(folder, "poses.json"), "w") as f:
        json.dump(doc, f)
    code, _, err = run(capsys, "handeye", "solve", folder, "--server", server.target)
    assert code == 2
    assert "FAILED_PRECONDITION" in err and "at least 3" in err
    code, _, err = run(capsys, "handeye", "solve", folder, "--local")
    assert code == 2 and "dqpose handeye solve: error: base_flange: 2 poses" in err
    # a robot that never turned (its pose logged once and copied): the samples, by image
    with open(os.path.join(eye_in_hand, "poses.json")) as f:
        doc = json.load(f)
    for p in doc["poses"]:
        p["base_to_flange"] = doc["poses"][0]["base_to_flange"]
    with open(os.path.join(folder, "poses.json"), "w") as f:
        json.dump(doc, f)
    code, _, err = run(capsys, "handeye", "solve", folder, "--server", server.target)
    assert code == 2 and "FAILED_PRECONDITION" in err and "samples 0, 1" in err, err
    assert "pairs[0] = view_000.png, pairs[1] = view_001.png" in err


@pytest.mark.parametrize("edit, message", [
    (lambda d: os.remove(os.path.join(d, "poses.json")), "DIR: no poses.json or poses.csv"),
    (lambda d: os.remove(os.path.join(d, "intrinsics.json")), "--intrinsics: required"),
    (lambda d: os.remove(os.path.join(d, "view_003.png")),
     "1 image(s) not in"),
])
def test_bad_folders_say_what_is_missing(eye_in_hand, capsys, tmp_path, edit, message):
    folder = str(tmp_path / "bad")
    shutil.copytree(eye_in_hand, folder)
    edit(folder)
    code, _, err = run(capsys, "handeye", "solve", folder, "--local")
    assert code == 2 and message in err, err
    assert "Traceback" not in err


def test_refusals_before_any_work(capsys, tmp_path, eye_in_hand):
    code, _, err = run(capsys, "handeye", "capture", str(tmp_path / "a"), "--views", "3")
    assert code == 2 and "--views: at least 4" in err
    code, _, err = run(capsys, "handeye", "capture", str(tmp_path / "b"), "--arm", "ur:10.0.0.1")
    assert code == 2 and "--arm: a real arm needs --camera and --intrinsics" in err
    code, _, err = run(capsys, "handeye", "capture", str(tmp_path / "c"), "--arm", "piper:can0")
    assert code == 2 and "--arm: ur:HOST (a UR arm), got 'piper:can0'" in err
    code, _, err = run(capsys, "handeye", "capture", eye_in_hand)
    assert code == 2 and "already holds a capture" in err
    code, _, err = run(capsys, "handeye", "solve", str(tmp_path / "none"), "--local")
    assert code == 2 and "DIR: no such folder" in err
    code, _, err = run(capsys, "handeye", "solve", eye_in_hand, "--server", "127.0.0.1:1",
                       "--timeout", "2")
    assert code == 2 and "no answer from the server at 127.0.0.1:1" in err


def test_capture_on_an_arm_given_by_address_with_a_camera_source(eye_in_hand, capsys, tmp_path):
    """The real-arm path (--arm, --camera, --intrinsics), on the UR simulator started here and
    a folder of images as the camera: the arm moves under the default limits, each image is
    taken where the arm is read to be, and no truth is written."""
    frames = tmp_path / "frames"
    frames.mkdir()
    for i in range(4):
        shutil.copy(os.path.join(eye_in_hand, f"view_{i:03d}.png"), frames)
    folder = str(tmp_path / "real")
    code, out, err, start, stands = _capture_on_the_sim_arm(eye_in_hand, capsys, frames,
                                                            folder, 4)
    assert code == 0, err
    with open(os.path.join(folder, "poses.json")) as f:
        flanges = [_pose(p["base_to_flange"]) for p in json.load(f)["poses"]]
    assert sorted(os.listdir(folder)) == ["board.json", "intrinsics.json", "poses.json"] + \
        [f"view_{i:03d}.png" for i in range(4)]
    assert "view 3: rotation spread" in err
    # the poses saved are where the arm was read to be: the start, and the last where it stands
    np.testing.assert_allclose(dq.to_matrix(flanges[0]), dq.to_matrix(start), atol=1e-6)
    np.testing.assert_allclose(dq.to_matrix(flanges[-1]),
                               dq.to_matrix(dq.from_pose(*_ur_to_pose(stands))), atol=1e-6)
    for i in range(1, 4):        # and it moved between views
        assert np.linalg.norm(dq.to_pose(flanges[i])[1] - dq.to_pose(flanges[i - 1])[1]) > 0.01


def _capture_on_the_sim_arm(eye_in_hand, capsys, frames, folder: str, views: int):
    """``dqpose handeye capture`` of the real-arm path on a UR simulator started at the first
    pose of the eye_in_hand capture, with the images in ``frames`` as the camera: ``(code, out,
    err, the start pose, where the arm stands at the end)``."""
    from dqpose.drivers.rotvec import rotvec_from_pose
    from dqpose.drivers.sim.ur import URSimProcess
    with open(os.path.join(eye_in_hand, "poses.json")) as f:
        start = _pose(json.load(f)["poses"][0]["base_to_flange"])
    with URSimProcess() as sim:
        sim.set_pose(rotvec_from_pose(start))
        code, out, err = run(capsys, "handeye", "capture", folder, "--arm", f"ur:{sim.host}",
                             "--camera", str(frames), "--intrinsics",
                             os.path.join(eye_in_hand, "intrinsics.json"), "--views", str(views))
        return code, out, err, start, sim.state()["pose"]


def _ur_to_pose(p6):
    from dqpose.drivers.rotvec import pose_from_rotvec
    return dq.to_pose(pose_from_rotvec(np.asarray(p6, dtype=float)))


def test_a_capture_that_loses_the_board_stops_and_keeps_what_it_took(eye_in_hand, capsys,
                                                                     tmp_path, monkeypatch):
    import cv2

    from dqpose.cli import handeye_capture
    monkeypatch.setattr(handeye_capture, "MAX_MISSES", 2)
    frames = tmp_path / "frames"
    frames.mkdir()
    shutil.copy(os.path.join(eye_in_hand, "view_000.png"), frames / "a.png")
    for name in ("b.png", "c.png", "d.png"):           # the board gone from the view
        cv2.imwrite(str(frames / name), np.full((480, 640), 110, np.uint8))
    folder = str(tmp_path / "lost")
    code, out, err, _, _ = _capture_on_the_sim_arm(eye_in_hand, capsys, frames, folder, 8)
    assert code == 2
    assert "the board was not detected in 2 views in a row" in err and "3 views saved" in err
    with open(os.path.join(folder, "poses.json")) as f:
        assert [p["image"] for p in json.load(f)["poses"]] == \
            ["view_000.png", "view_001.png", "view_002.png"]


def test_the_report_counts_the_views_it_used(eye_in_hand, capsys, tmp_path):
    """A view whose robot pose is 5 mm off is left out by the robust solve: the report's first
    line counts it out (it said "8 views used of 8"), and a clean capture leaves none out (the
    first view, head-on to the board, was left out of every capture)."""
    code, stdout, err = run(capsys, "handeye", "solve", eye_in_hand, "--local",
                            "--report", str(tmp_path / "clean.txt"),
                            "--plot", str(tmp_path / "clean.png"), "-o", str(tmp_path / "c.json"))
    assert code == 0, err
    assert stdout.splitlines()[0].startswith("hand-eye calibration, eye_in_hand: 8 views used "
                                             "of 8 images"), stdout
    assert "left out:" not in stdout and "warning:" not in stdout, stdout
    folder = str(tmp_path / "moved")
    shutil.copytree(eye_in_hand, folder)
    with open(os.path.join(folder, "poses.json")) as f:
        doc = json.load(f)
    doc["poses"][3]["base_to_flange"]["position"]["x"] += 0.005
    with open(os.path.join(folder, "poses.json"), "w") as f:
        json.dump(doc, f)
    code, stdout, err = run(capsys, "handeye", "solve", folder, "--local")
    assert code == 0, err
    left_out = [line for line in stdout.splitlines() if "left out:" in line]
    assert any("view_003.png" in line for line in left_out), stdout
    assert stdout.splitlines()[0].startswith(
        f"hand-eye calibration, eye_in_hand: {8 - len(left_out)} views used of 8 images "
        f"({len(left_out)} left out by the robust solve"), stdout
