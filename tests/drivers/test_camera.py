"""CharucoCamera (real OpenCV detection) on images rendered by the simulated camera."""
import json
import math

import cv2
import numpy as np
import pytest

from dqpose import dq, lie
from dqpose.drivers.camera import (
    BoardSpec,
    CharucoCamera,
    Detection,
    Intrinsics,
    LiveFrames,
    Rejection,
    load_board,
    load_intrinsics,
    marker_free_reach,
    open_frames,
    pnp_chart,
)
from dqpose.drivers.sim import camera as simcam
from dqpose.drivers.sim.camera import DEFAULT_INTRINSICS, BoardRenderer, look_at, random_view
from tests._handeye import near_side_pull
from tests._polling import Slowdown


def errors(T_est, T_true):
    """(rotation error in degrees, translation error in mm)."""
    E = dq.mul(dq.inv(T_true), T_est)
    q, _ = dq.to_pose(E)
    ang = math.degrees(2 * math.acos(min(1.0, abs(q[0]))))
    d = np.linalg.norm(dq.to_pose(T_est)[1] - dq.to_pose(T_true)[1]) * 1000
    return ang, d


@pytest.fixture(scope="module")
def renderer():
    return BoardRenderer()


@pytest.fixture
def cam(renderer):
    return CharucoCamera(renderer.intrinsics)


FRONT = look_at([0.14, 0.1, -0.45], [0.14, 0.1, 0.0])
OBLIQUE = look_at([0.3, 0.25, -0.35], [0.14, 0.1, 0.0])


def test_renderer_puts_corners_where_the_pose_projects_them(renderer):
    board = BoardSpec()
    img = renderer.render(OBLIQUE)
    det = cv2.aruco.CharucoDetector(board.cv_board)
    corners, ids, _, _ = det.detectBoard(img)
    obj, seen = board.cv_board.matchImagePoints(corners, ids)
    M = dq.to_matrix(OBLIQUE)
    rvec, _ = cv2.Rodrigues(M[:3, :3])
    proj, _ = cv2.projectPoints(obj, rvec, M[:3, 3], renderer.intrinsics.K, None)
    err = np.linalg.norm(proj.reshape(-1, 2) - seen.reshape(-1, 2), axis=1)
    assert len(err) == board.n_corners
    assert np.median(err) < 0.1


def test_twenty_random_views_are_accurate(renderer, cam):
    rng = np.random.default_rng(20)
    rot, trans = [], []
    for _ in range(20):
        T = random_view(rng)
        d = cam.detect(renderer.render(T))
        assert isinstance(d, Detection), d
        a, t = errors(d.pose, T)
        rot.append(a)
        trans.append(t)
    print(f"\n20 clean views: median {np.median(rot):.4f} deg / {np.median(trans):.4f} mm, "
          f"max {np.max(rot):.4f} deg / {np.max(trans):.4f} mm")
    assert np.median(rot) <= 0.05
    assert np.median(trans) <= 0.2


def test_covariance_matches_the_errors(renderer, cam):
    """Squared Mahalanobis distances of the true errors average ~6 (chi-square, 6 dof) if the
    covariance is right; a wrong tangent convention or a wrong scale is far off."""
    rng = np.random.default_rng(21)
    m2 = []
    for _ in range(20):
        T = random_view(rng)
        d = cam.detect(renderer.render(T, noise=3.0, blur=0.6, rng=rng))
        assert d.ok, d
        delta = 2 * dq.log(dq.mul(dq.inv(d.pose), T))   # T_true = T_est Exp(delta)
        m2.append(delta @ np.linalg.solve(d.covariance, delta))
    assert 2.0 < np.mean(m2) < 15.0


def test_corners_share_no_pull_toward_either_side_of_the_board(renderer, cam):
    """OpenCV refines a ChArUco corner in a window that reaches into the markers beside it; under
    perspective their edges pull every corner of a view toward the board's far side (an error
    the corners share, so each view's pose claimed 1.3-1.5x too much along the directions the
    corners fix best, and hand-eye end to end had mean NEES 8.9). The detector's own refinement
    keeps its windows off the markers: over 100 clean oblique views the mean pull is within 3
    standard errors of zero, where OpenCV's corners are more than 3 away on the far side (so
    the renders still show the effect this test looks for)."""
    rng = np.random.default_rng(11)
    K = renderer.intrinsics.K
    ours, opencvs = [], []
    for _ in range(100):
        T = random_view(rng, max_tilt_deg=45.0, max_roll_deg=90.0)
        img = renderer.render(T)
        d = cam.detect(img)
        assert d.ok, d
        ours.append(near_side_pull(T, d.object_points, d.image_points, K))
        obj, raw, _ = cam._points(img)          # OpenCV's corners, before ours
        opencvs.append(near_side_pull(T, obj, raw, K))
    ours, opencvs = np.array(ours), np.array(opencvs)
    se = ours.std(ddof=1) / np.sqrt(len(ours))
    se_cv = opencvs.std(ddof=1) / np.sqrt(len(opencvs))
    print(f"\nmean pull toward the near side: ours {ours.mean():+.4f} px (SE {se:.4f}), "
          f"OpenCV's {opencvs.mean():+.4f} px (SE {se_cv:.4f})")
    assert abs(ours.mean()) < 3 * se
    assert opencvs.mean() < -3 * se_cv


def test_marker_free_reach():
    """The window half-size at which the corner's window first touches a marker: a board seen
    square-on at s px per metre reaches the markers at gap * s along its axes, and at 45 deg of
    roll (the window's corners along the board's axes, its sides' midpoints toward the markers)
    at sqrt(2) * gap * s; any local scale agrees with a dense search of the window's edge."""
    gap, s = 0.005, 1200.0
    c, si = math.cos(math.pi / 4), math.sin(math.pi / 4)
    J = np.array([s * np.eye(2), s * np.array([[c, -si], [si, c]])])
    assert np.allclose(marker_free_reach(J, gap), [gap * s, math.sqrt(2) * gap * s])
    J = np.random.default_rng(3).normal(size=(50, 2, 2)) * s
    t = np.linspace(-1, 1, 20001)
    one = np.ones_like(t)
    edge = np.concatenate([np.column_stack(e) for e in ((one, t), (-one, t), (t, one), (t, -one))])
    for Jk, r in zip(J, marker_free_reach(J, gap)):
        d = edge @ np.linalg.inv(Jk).T
        assert r == pytest.approx(gap / np.max(np.min(np.abs(d), axis=1)), rel=1e-3)


def test_pnp_chart_is_the_derivative_of_the_se3_right_perturbation():
    """Finite differences of OpenCV's (rvec, tvec) of T * Exp(xi), Exp the SE(3) exponential."""
    T = OBLIQUE
    M = dq.to_matrix(T)
    rvec = cv2.Rodrigues(M[:3, :3])[0].ravel()

    def params(xi):
        Mx = dq.to_matrix(dq.mul(T, lie.se3_exp(xi)))
        r = cv2.Rodrigues(Mx[:3, :3])[0].ravel()
        return np.concatenate([r, Mx[:3, 3]])

    h = 1e-6
    num = np.column_stack([(params(h * e) - params(-h * e)) / (2 * h) for e in np.eye(6)])
    assert np.allclose(pnp_chart(rvec), num, atol=1e-8)
    # the factor matters: the identity (OpenCV's parameters taken as the tangent) is far off
    assert not np.allclose(np.eye(6), num, atol=0.1)


def test_reported_covariance_is_the_se3_right_perturbation_covariance(renderer, cam):
    """Recompute s^2 (J^T J)^-1 with J by finite differences of the corners' projections of
    T * Exp(xi) (SE(3) exponential): the detector's covariance is exactly that."""
    d = cam.detect(renderer.render(OBLIQUE, noise=3.0, blur=0.6, rng=np.random.default_rng(4)))
    assert d.ok, d
    K = renderer.intrinsics.K

    def project(xi):
        Mx = dq.to_matrix(dq.mul(d.pose, lie.se3_exp(xi)))
        p, _ = cv2.projectPoints(d.object_points, cv2.Rodrigues(Mx[:3, :3])[0], Mx[:3, 3], K,
                                 None)
        return p.ravel()

    h = 1e-7
    J = np.column_stack([(project(h * e) - project(-h * e)) / (2 * h) for e in np.eye(6)])
    # the pixel variance whose inverse is unbiased (the module's doc): sum r^2 / (2N - 8)
    s2 = max(d.rms ** 2 * d.n_points / (2 * d.n_points - 8), cam.min_pixel_sigma ** 2)
    expected = s2 * np.linalg.inv(J.T @ J)
    assert np.allclose(d.covariance, expected, rtol=1e-5, atol=0)


def test_few_corners_give_an_honest_mean_nees():
    """150 random views of a board of 6 corners (``nu = 2N - 6 = 6`` residual degrees of
    freedom): the mean NEES of the detections against their truth is about 6. With the pixel
    variance taken as ``sum r^2 / nu`` its inverse was ``nu / (nu - 2) = 1.5`` times too large on
    average: the mean NEES was 7.2-10.0 over seeds 0-7 of 100 views (4.8-6.7 with ``2N - 8``)."""
    board = BoardSpec(squares=(4, 3))
    intr = Intrinsics(K=np.array([[300.0, 0, 159.5], [0, 300.0, 119.5], [0, 0, 1]]),
                      size=(320, 240))
    small, cam = BoardRenderer(intrinsics=intr, board=board), CharucoCamera(intr, board)
    rng = np.random.default_rng(0)
    nees = []
    for _ in range(150):
        T = random_view(rng, board, distance=(0.25, 0.4))
        d = cam.detect(small.render(T, blur=0.8, noise=6.0, rng=rng))
        if d.ok:
            assert d.n_points == board.n_corners
            xi = lie.se3_log(dq.mul(dq.inv(d.pose), T))
            nees.append(xi @ np.linalg.solve(d.covariance, xi))
    assert len(nees) >= 140
    print(f"\nmean NEES of {len(nees)} views of 6 corners: {np.mean(nees):.2f}")
    assert 4.8 < np.mean(nees) < 7.2


def test_covariance_matches_monte_carlo_of_renders():
    """200 noisy renders of one oblique view: the second moment of the true error, in the
    right-perturbation convention (T_true = T_est Exp(xi)), whitened by the reported covariance,
    is about the identity. The reported covariance comes from the residuals, so it covers the
    detector's systematic corner errors too: compare the second moment about the truth, not
    about the mean. Taking the covariance in the left (camera-frame) convention instead puts
    eigenvalues in the hundreds."""
    intr = Intrinsics(K=np.array([[300.0, 0, 159.5], [0, 300.0, 119.5], [0, 0, 1]]),
                      size=(320, 240))
    small = BoardRenderer(intrinsics=intr)
    cam = CharucoCamera(intr)
    w, h = cam.board.extent
    T = look_at([w / 2 + 0.15, h / 2 - 0.1, -0.3], [w / 2, h / 2, 0], [0.3, -1, 0])
    rng = np.random.default_rng(0)
    xi, covs = [], []
    for _ in range(200):
        d = cam.detect(small.render(T, blur=1.0, noise=12.0, rng=rng))
        assert d.ok, d
        xi.append(lie.se3_log(dq.mul(dq.inv(d.pose), T)))
        covs.append(d.covariance)
    xi, cov = np.array(xi), np.mean(covs, axis=0)
    second = xi.T @ xi / len(xi)

    def whitened_eigenvalues(C):
        Li = np.linalg.inv(np.linalg.cholesky(C))
        return np.linalg.eigvalsh(Li @ second @ Li.T)

    ev = whitened_eigenvalues(cov)
    print(f"\nwhitened eigenvalues of the error's second moment: {np.round(ev, 2)}")
    # Seeds 0-4 and 7 gave mean NEES 0.87-1.0 and eigenvalues 0.39-2.15: the detector's
    # systematic corner error is one draw per view, so single directions spread more than
    # 200 samples of noise alone would.
    assert 0.25 < ev.min() and ev.max() < 3.0
    assert 0.7 < np.trace(np.linalg.solve(cov, second)) / 6 < 1.4
    assert whitened_eigenvalues(lie.cov_right_to_left(T, cov)).max() > 20


def test_covariance_positive_definite_and_grows_with_noise(renderer, cam):
    traces = []
    for noise in (0.0, 8.0, 24.0):
        d = cam.detect(renderer.render(OBLIQUE, noise=noise, rng=np.random.default_rng(0)))
        assert d.ok, d
        assert d.covariance.shape == (6, 6)
        assert np.allclose(d.covariance, d.covariance.T)
        assert np.min(np.linalg.eigvalsh(d.covariance)) > 0
        traces.append(np.trace(d.covariance))
    assert traces[0] < traces[1] < traces[2]


def test_board_mostly_out_of_frame_is_rejected(renderer, cam):
    # close up, aimed past the top-left corner of the board
    img = renderer.render(look_at([-0.05, -0.05, -0.25], [-0.05, -0.05, 0.0]))
    r = cam.detect(img)
    assert isinstance(r, Rejection)
    assert r.reason in ("too_few_corners", "no_board")
    assert r.n_points < cam.min_corners
    assert cam.last_rejection is r


def test_heavily_occluded_board_is_rejected(renderer, cam):
    img = renderer.render(FRONT)
    occluded = np.full_like(img, 255)
    occluded[150:300, 200:360] = img[150:300, 200:360]
    r = cam.detect(occluded)
    assert isinstance(r, Rejection) and r.reason == "too_few_corners"
    assert 0 < r.n_points < 6
    assert f"{r.n_points} < 6" in r.message
    # the same view unoccluded is fine
    assert cam.detect(img).ok


def test_collinear_corners_are_rejected():
    board = BoardSpec(squares=(7, 2))     # one row of inner corners
    r = BoardRenderer(board)
    cam = CharucoCamera(r.intrinsics, board)
    res = cam.detect(r.render(look_at([0.14, 0.04, -0.4], [0.14, 0.04, 0.0])))
    assert isinstance(res, Rejection) and res.reason == "collinear", res


def test_large_reprojection_error_is_rejected(renderer):
    wrong = Intrinsics(K=renderer.intrinsics.K, dist=[0.8, 0, 0, 0, 0], size=(640, 480))
    res = CharucoCamera(wrong).detect(renderer.render(OBLIQUE))
    assert isinstance(res, Rejection) and res.reason == "reprojection", res


def test_no_board_is_rejected(cam):
    res = cam.detect(np.full((480, 640), 128, np.uint8))
    assert isinstance(res, Rejection) and res.reason == "no_board"


def test_single_marker_close_is_accurate_and_far_is_ambiguous():
    board = BoardSpec(kind="marker", marker_length=0.05, marker_id=7)
    r = BoardRenderer(board)
    cam = CharucoCamera(r.intrinsics, board)
    rng = np.random.default_rng(5)
    near = [look_at([0.08, 0.05, -0.3], [0, 0, 0]), look_at([0.0, 0.0, -0.3], [0, 0, 0]),
            look_at([-0.1, 0.02, -0.25], [0, 0, 0])]
    for T in near:
        d = cam.detect(r.render(T, noise=2.0, rng=rng))
        assert d.ok, d
        a, t = errors(d.pose, T)
        assert a < 1.0 and t < 2.0
    far = cam.detect(r.render(look_at([0.1, 0.05, -1.0], [0, 0, 0]), noise=2.0, rng=rng))
    assert isinstance(far, Rejection) and far.reason == "ambiguous", far
    # a marker id not in view
    other = CharucoCamera(r.intrinsics, BoardSpec(kind="marker", marker_length=0.05,
                                                  marker_id=8))
    res = other.detect(r.render(near[0]))
    assert res.reason == "no_board" and "marker 8 not in view" in res.message


def test_image_folder_source_and_sim_cli(tmp_path):
    out = tmp_path / "views"
    assert simcam.main(["--out", str(out), "--count", "4", "--seed", "9"]) == 0
    truth = json.loads((out / "poses.json").read_text())
    intr_file = tmp_path / "intrinsics.json"
    intr_file.write_text(json.dumps({"K": truth["K"], "dist": truth["dist"],
                                     "image_size": truth["image_size"]}))
    with CharucoCamera(str(intr_file), source=str(out), name="cam0") as cam:
        ms = list(cam)
        assert cam.exhausted and cam.read() is None
    assert len(ms) == 4
    for m, name in zip(ms, sorted(truth["T_camera_board"])):
        assert m.source == "cam0" and m.covariance.shape == (6, 6)
        a, t = errors(m.pose, np.array(truth["T_camera_board"][name]))
        assert a < 0.2 and t < 1.0


def test_video_file_source(tmp_path, renderer):
    path = str(tmp_path / "clip.avi")
    w = cv2.VideoWriter(path, cv2.VideoWriter_fourcc(*"MJPG"), 10, (640, 480), False)
    if not w.isOpened():
        pytest.skip("this OpenCV build cannot write MJPG video")
    for _ in range(3):
        w.write(renderer.render(OBLIQUE))
    w.release()
    with CharucoCamera(renderer.intrinsics, source=path) as cam:
        ms = list(cam)
    assert len(ms) == 3
    a, t = errors(ms[0].pose, OBLIQUE)
    assert a < 0.5 and t < 2.0      # JPEG compression costs some accuracy


def test_unreadable_and_missing_inputs_give_clear_errors(tmp_path, renderer):
    folder = tmp_path / "imgs"
    folder.mkdir()
    cv2.imwrite(str(folder / "a.png"), renderer.render(OBLIQUE))
    (folder / "b.png").write_text("this is not a PNG")
    cam = CharucoCamera(renderer.intrinsics, source=str(folder))
    assert cam.read() is not None
    with pytest.raises(ValueError, match=r"image: cannot decode .*b\.png"):
        cam.read()
    with pytest.raises(ValueError, match="source: no such file or folder"):
        CharucoCamera(renderer.intrinsics, source=str(tmp_path / "missing"))
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(ValueError, match="source: no images"):
        CharucoCamera(renderer.intrinsics, source=str(empty))
    (tmp_path / "clip.mp4").write_text("not a video")
    with pytest.raises(ValueError, match="source: cannot open video"):
        open_frames(str(tmp_path / "clip.mp4"))
    with pytest.raises(ValueError, match="image: expected"):
        CharucoCamera(renderer.intrinsics).detect(np.zeros((4, 4), np.float32))
    with pytest.raises(ValueError, match="source: this camera has no frame source"):
        CharucoCamera(renderer.intrinsics).read()


def test_intrinsics_files(tmp_path):
    K = DEFAULT_INTRINSICS.K
    # OpenCV FileStorage YAML, as written by calibration tools
    p = str(tmp_path / "cv.yaml")
    fs = cv2.FileStorage(p, cv2.FILE_STORAGE_WRITE)
    fs.write("camera_matrix", K)
    fs.write("distortion_coefficients", np.array([[0.1, -0.2, 0.0, 0.0, 0.05]]))
    fs.write("image_width", 640)
    fs.write("image_height", 480)
    fs.release()
    intr = load_intrinsics(p)
    assert np.allclose(intr.K, K) and np.allclose(intr.dist, [0.1, -0.2, 0, 0, 0.05])
    assert intr.size == (640, 480)
    # ROS camera_info style
    ros = tmp_path / "ros.yaml"
    ros.write_text("image_width: 800\nimage_height: 600\ncamera_matrix:\n  rows: 3\n  cols: 3\n"
                   "  data: [600, 0, 399.5, 0, 600, 299.5, 0, 0, 1]\n"
                   "distortion_coefficients:\n  rows: 1\n  cols: 5\n  data: [0, 0, 0, 0, 0]\n")
    assert load_intrinsics(str(ros)).size == (800, 600)
    bad = tmp_path / "bad.yaml"
    bad.write_text("K: [[1, 2], [3, 4]]\nimage_size: [640, 480]\n")
    with pytest.raises(ValueError, match="intrinsics.K: expected 9 numbers"):
        load_intrinsics(str(bad))
    bad.write_text("K: [600, 0, 320, 0, 600, 240, 0, 0, 1]\n")
    with pytest.raises(ValueError, match="image_size"):
        load_intrinsics(str(bad))
    bad.write_text("K: [[[\n")
    with pytest.raises(ValueError, match="cannot parse"):
        load_intrinsics(str(bad))
    with pytest.raises(ValueError, match="no such file"):
        load_intrinsics(str(tmp_path / "nope.yaml"))
    with pytest.raises(ValueError, match="K: expected"):
        Intrinsics(K=-np.eye(3))


def test_board_files_and_bad_boards(tmp_path):
    p = tmp_path / "board.yaml"
    p.write_text("squares: [5, 4]\nsquare_length: 0.03\nmarker_length: 0.022\n"
                 "dictionary_name: DICT_4X4_50\n")
    b = load_board(str(p))
    assert b.squares == (5, 4) and b.n_corners == 12
    p.write_text("squares: [5, 4]\ncolour: red\n")
    with pytest.raises(ValueError, match="unknown keys"):
        load_board(str(p))
    with pytest.raises(ValueError, match="dictionary_name"):
        BoardSpec(dictionary_name="DICT_NOPE")
    with pytest.raises(ValueError, match="marker_length"):
        BoardSpec(square_length=0.02, marker_length=0.03)


def test_renderer_bad_input(renderer):
    with pytest.raises(ValueError, match="behind the camera"):
        renderer.render(look_at([0.14, 0.1, 0.45], [0.14, 0.1, 1.0]))  # looking away
    with pytest.raises(ValueError, match="dist"):
        BoardRenderer(intrinsics=Intrinsics(K=DEFAULT_INTRINSICS.K, dist=[0.1, 0, 0, 0, 0]))


class _StandInDevice:
    """Stands in for a camera device (none exists on a test machine): ``read`` blocks until a
    frame is pushed, like ``cv2.VideoCapture.read`` on a live camera; None ends the stream."""

    def __init__(self):
        import queue
        self.q: "queue.Queue" = queue.Queue()

    def push(self, item) -> None:
        self.q.put(item)

    def read(self, timeout=None):
        item = self.q.get()
        if isinstance(item, Exception):
            raise item
        return item

    def close(self) -> None:
        self.q.put(None)


def test_live_source_times_out_then_delivers_the_newest_frame(renderer):
    import time
    device = _StandInDevice()
    with CharucoCamera(renderer.intrinsics, source=LiveFrames(device), name="wrist") as cam:
        slow = Slowdown().start()
        t0 = time.monotonic()
        assert cam.read(timeout=0.2) is None                # the camera stalls
        waited = time.monotonic() - t0
        assert 0.2 <= waited < 1.5 * slow.stop()            # stretched on a loaded machine
        assert cam.last_rejection.reason == "no_frame" and "wrist" in str(cam.last_rejection)
        assert not cam.exhausted
        for T in (FRONT, OBLIQUE, FRONT, OBLIQUE):          # frames arrive faster than we read
            device.push(renderer.render(T))
        deadline = time.monotonic() + 5
        while not device.q.empty() and time.monotonic() < deadline:
            time.sleep(0.01)
        time.sleep(0.05)
        m = cam.read(timeout=2.0)
        assert m is not None and errors(m.pose, OBLIQUE)[0] < 0.1   # the last one pushed
        assert cam.frames.dropped == 3
        assert cam.read(timeout=0.1) is None and cam.last_rejection.reason == "no_frame"
        device.push(None)                                   # the device goes away
        assert cam.read(timeout=2.0) is None and cam.exhausted


def test_live_source_errors_reach_the_reader(renderer):
    device = _StandInDevice()
    with CharucoCamera(renderer.intrinsics, source=LiveFrames(device)) as cam:
        device.push(OSError("camera unplugged"))
        with pytest.raises(OSError, match="camera unplugged"):
            cam.read(timeout=2.0)


def test_a_frame_source_object_is_used_as_it_is(renderer):
    device = _StandInDevice()
    device.push(renderer.render(FRONT))
    device.push(None)
    with CharucoCamera(renderer.intrinsics, source=device) as cam:
        ms = list(cam)
    assert len(ms) == 1 and errors(ms[0].pose, FRONT)[0] < 0.1
