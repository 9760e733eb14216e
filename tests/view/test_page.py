"""``dqpose view FILE.mcap`` in a real headless browser (Chromium from Debian's packages, software
WebGL): a recording of two fused bodies with large covariances and a plan, served by a real
``dqpose view`` process, rendered to a PNG; the ellipsoids' and the plan's colours cover enough
pixels, where the same page without bodies (rendered the same way) has none of them and is not
blank either. A robot cell's recording (``_cell.py``) opened as its folder: what is drawn covers
at least a quarter of the view and every frame's name is drawn. In process: each arm at its base
(or aside when the file does not place it), the ellipsoids' scale chosen and changed, the
bodies' trails."""
from __future__ import annotations

import json
import shutil
import subprocess
import sys

import numpy as np
import pytest

from dqpose import dq
from tests.cli._cli import ROOT

pytest.importorskip("viser", reason="the [view] extra (pip install -e '.[view]')")
pytest.importorskip("foxglove", reason="the [record] extra")
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
pytestmark = pytest.mark.skipif(CHROMIUM is None, reason="no Chromium: apt-get install -y "
                                                         "chromium (.ci/run installs it)")


def record(directory) -> str:
    """A recording: two Fuse calls (bodies ``box`` and ``cup``, position sigmas of centimetres)
    and a plan, through a real server."""
    from dqpose.record.recorder import Recorder
    from dqpose.rpc.client import Client
    from dqpose.rpc.server import ServerConfig
    from tests.rpc._grpc_server import ServerThread

    recorder = Recorder(directory)
    cov = np.diag([1e-3, 1e-3, 1e-3, 0.08 ** 2, 0.05 ** 2, 0.03 ** 2])
    with ServerThread(ServerConfig(port=0, recorder=recorder)) as s:
        c = Client(s.target)
        for body, x in (("box", 0.0), ("cup", 0.6)):
            poses = dq.from_pose(np.array([[1.0, 0, 0, 0]] * 2),
                                 np.array([[x, 0.0, 0.3], [x + 0.01, 0.0, 0.3]]))
            c.fuse(poses, np.array([cov, cov]), body=body)
        path = dq.from_pose(np.array([[1.0, 0, 0, 0]] * 20),
                            np.stack([np.linspace(0, 0.6, 20), np.full(20, -0.3),
                                      np.full(20, 0.3)], axis=1))
        recorder.plan("Plan", path)
    (f,) = recorder.files
    return f


def record_arm(directory) -> str:
    """A recording of an arm's run through the recorder, as a server records it: the plan's
    path (a line along x at y = 0.3), an Execute call whose feedback's actual poses trail the
    plan 2 cm off it (along y = 0.32), then two WatchArm states at its end."""
    from dqpose.record.recorder import Recorder
    from dqpose.rpc._proto.dqpose.v1 import trajectories_pb2 as tpb
    from dqpose.rpc.geometry import dq_to_pose

    recorder = Recorder(directory)
    xs = np.linspace(0.0, 0.6, 30)
    level = np.array([[1.0, 0, 0, 0]] * 30)
    recorder.plan("ur", dq.from_pose(level, np.stack([xs, np.full(30, 0.3),
                                                      np.full(30, 0.2)], axis=1)))
    call = recorder.call("dqpose.v1.Trajectories/Execute", tpb.ExecuteRequest,
                         tpb.ExecutionFeedback)
    call.request(tpb.ExecuteRequest(arm="ur"))
    for k, x in enumerate(xs):
        fb = tpb.ExecutionFeedback(time=0.1 * k, state=tpb.EXECUTION_WORKING)
        dq_to_pose(dq.from_pose([1.0, 0, 0, 0], [x, 0.3, 0.2]), fb.commanded)
        dq_to_pose(dq.from_pose([1.0, 0, 0, 0], [x, 0.32, 0.2]), fb.actual)
        call.answer(fb)
    call.end("OK")
    watch = recorder.call("dqpose.v1.Trajectories/WatchArm", tpb.GetArmRequest, tpb.ArmState)
    watch.request(tpb.GetArmRequest(arm="ur"))
    for _ in range(2):
        st = tpb.ArmState(arm="ur", state=tpb.EXECUTION_FINISHED)
        dq_to_pose(dq.from_pose([1.0, 0, 0, 0], [0.6, 0.32, 0.2]), st.pose)
        watch.answer(st)
    watch.end("CANCELLED")
    recorder.close()
    (f,) = recorder.files
    return f


def screenshot(url: str, out, ready=None, attempts: int = 3) -> np.ndarray:
    """The page at ``url`` as headless Chromium draws it (1280x800, RGB 0..255). On a loaded
    machine Chromium can take its picture before the page has drawn what the viewer sent it
    (the 3D view blank, or the grid without the bodies: the scene's messages still on their way
    over the WebSocket while Chromium's virtual time ran out); that picture says nothing about
    the page, so it is taken again, at most ``attempts`` times, until ``ready(img)`` (default:
    the 3D view drawn) holds. A page that never draws what a test looks for still fails it."""
    import matplotlib.image

    for _ in range(attempts):
        subprocess.run([CHROMIUM, "--headless=new", "--use-angle=swiftshader", "--no-sandbox",
                        "--disable-gpu-sandbox", "--hide-scrollbars",
                        "--virtual-time-budget=15000", f"--screenshot={out}",
                        "--window-size=1280,800", url], check=True, capture_output=True,
                       timeout=180)
        img = (matplotlib.image.imread(str(out))[..., :3] * 255).astype(int)
        if (ready or drawn)(img):
            break
    return img


#: the rows below the page's overlays (the controls, a notice of software WebGL with an orange
#: bar): the 3D view alone
SCENE_ROWS = slice(200, None)


def drawn(img: np.ndarray) -> bool:
    """Whether the 3D view was drawn: even an empty scene has its grid."""
    return bool(img[SCENE_ROWS].std() > 1.0)


def ellipsoid_pixels(img: np.ndarray) -> int:
    """Pixels of the ellipsoids' hue (red and blue above green) at any lightness: translucent and
    lit, they come out anywhere from magenta to a pale pink (255, 223, 250) depending on the
    renderer; the grid and the background are grey (r = g = b)."""
    img = img[SCENE_ROWS]
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    return int(np.sum((r - g > 20) & (b - g > 20)))


def plan_pixels(img: np.ndarray) -> int:
    """Pixels of the plans' orange hue (red above green above blue) at any lightness: the lines
    come out anywhere from orange to a pale peach (248, 215, 161); the grid is grey, the frame's
    red axis has green = blue, the ellipsoids blue above green."""
    img = img[SCENE_ROWS]
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    return int(np.sum((r - g > 20) & (g - b > 20)))


def actual_pixels(img: np.ndarray) -> int:
    """Pixels of an arm's actual path's cyan hue (green and blue above red, close to each
    other) at any lightness: the line comes out (120, 200, 200) to (160, 200, 240); the time
    slider and the axes' blue have green well below blue."""
    img = img[SCENE_ROWS]
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    return int(np.sum((g - r > 20) & (b - r > 20) & (np.abs(g - b) < 50)))


def empty_screenshot(tmp_path) -> np.ndarray:
    """The page without bodies, plans or arms, rendered as the others."""
    from dqpose.view.page import Page
    from dqpose.view.timeline import Timeline

    empty_page = Page(Timeline(0, 0, {}, []), port=0)
    try:
        return screenshot(f"http://127.0.0.1:{empty_page.port}", tmp_path / "empty.png")
    finally:
        empty_page.close()


def view(path):
    proc = subprocess.Popen([sys.executable, "-m", "dqpose.cli", "view", path, "--port",
                             "0"], cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            text=True)
    while True:
        line = proc.stderr.readline()
        assert line, "dqpose view ended before serving"
        if line.startswith("{"):
            return proc, json.loads(line)


#: pixels of the recorded scene's two ellipsoids, and of the arm's actual path, at the least
ELLIPSOIDS = 2000
ACTUAL_PATH = 150


def test_the_page_draws_the_bodies_ellipsoids(tmp_path):
    path = record(tmp_path / "rec")
    proc, info = view(path)
    try:
        assert (info["bodies"], info["plans"]) == (["box", "cup"], ["Plan"])
        # retaken until both bodies' ellipsoids are in (a picture of the scene half arrived
        # says nothing about the page)
        scene = screenshot(info["url"], tmp_path / "scene.png",
                           lambda img: drawn(img) and ellipsoid_pixels(img) > ELLIPSOIDS)
    finally:
        proc.terminate()
        proc.wait(30)
    empty = empty_screenshot(tmp_path)
    assert drawn(empty) and drawn(scene), "a page's 3D view rendered blank"
    # the empty scene has a few orange-ish pixels of its own (the world frame's axes blended
    # into the grid): the plan must add well more than that
    assert ellipsoid_pixels(empty) < 50 and plan_pixels(empty) < 150
    assert ellipsoid_pixels(scene) > ELLIPSOIDS, ellipsoid_pixels(scene)
    assert plan_pixels(scene) > plan_pixels(empty) + 150, (plan_pixels(scene), plan_pixels(empty))


def test_the_slider_shows_the_scene_as_it_was(tmp_path):
    from dqpose.record.reader import read
    from dqpose.view.page import Page
    from dqpose.view.timeline import timeline

    tl = timeline(read(record(tmp_path)))
    page = Page(tl, port=0)
    try:
        box, cup = tl.tracks["box"].ns[0], tl.tracks["cup"].ns[0]
        (_, planned, _), = tl.plans
        assert box < cup < planned
        seen = []
        for ns in (box - 1, box, cup, planned):
            page.slider.value = (ns - tl.start) * 1e-9
            page.show(page.ns(page.slider.value))
            seen.append((page.frames["box"].visible, page.ellipsoids["box"].visible,
                         page.frames["cup"].visible, "Plan" in page.plans
                         and page.plans["Plan"].visible))
        assert seen == [(False, False, False, False), (True, True, False, False),
                        (True, True, True, False), (True, True, True, True)]
        # the ellipsoid's half axes: 3 sigma of the fused position (sigmas / sqrt 2)
        assert sorted(page.ellipsoids["box"].scale) == pytest.approx(
            sorted(3 * np.array([0.08, 0.05, 0.03]) / np.sqrt(2)), rel=1e-6)
    finally:
        page.close()


def test_the_page_draws_the_arms_actual_path_beside_its_plan(tmp_path):
    path = record_arm(tmp_path / "rec")
    empty = empty_screenshot(tmp_path)
    proc, info = view(path)
    try:
        assert (info["bodies"], info["plans"], info["arms"]) == ([], ["ur"], ["ur"])
        # retaken until both lines are drawn (under load the plan's came after the path's)
        scene = screenshot(info["url"], tmp_path / "scene.png",
                           lambda img: drawn(img) and actual_pixels(img) > ACTUAL_PATH
                           and plan_pixels(img) > plan_pixels(empty) + 150)
    finally:
        proc.terminate()
        proc.wait(30)
    assert drawn(empty) and drawn(scene), "a page's 3D view rendered blank"
    assert actual_pixels(empty) < 50, actual_pixels(empty)
    assert actual_pixels(scene) > ACTUAL_PATH, actual_pixels(scene)
    assert plan_pixels(scene) > plan_pixels(empty) + 150, (plan_pixels(scene), plan_pixels(empty))


#: the 3D view of a 1280x800 window: the controls are docked right of column 955
VIEW_COLUMNS = 955
#: the overlays over the 3D view: the notice of software WebGL (top left), the axes gizmo
OVERLAYS = ((slice(0, 160), slice(0, 320)), (slice(730, 800), slice(0, 70)))


def _view(img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The 3D view's pixels and where no overlay covers them."""
    v = img[:, :VIEW_COLUMNS]
    free = np.ones(v.shape[:2], dtype=bool)
    for rows, cols in OVERLAYS:
        free[rows, cols] = False
    return v, free


def content_share(img: np.ndarray) -> float:
    """The share of the 3D view the bounding box of what the page draws covers: the coloured
    pixels (the ellipsoids, the frames' axes, the lines; the grid, the labels, the background
    and the shadows are grey)."""
    v, free = _view(img)
    ys, xs = np.nonzero((v.max(axis=-1) - v.min(axis=-1) > 40) & free)
    if not len(xs):
        return 0.0
    return (np.ptp(xs) + 1) * (np.ptp(ys) + 1) / (v.shape[0] * v.shape[1])


def label_count(img: np.ndarray) -> int:
    """How many words of dark grey text the 3D view shows (the labels' text; the grid's lines
    are lighter, every drawn thing is coloured): dark grey pixels, joined into words."""
    from scipy import ndimage

    v, free = _view(img)
    text = (v.max(axis=-1) <= 140) & (v.max(axis=-1) - v.min(axis=-1) < 25) & free
    words, n = ndimage.label(ndimage.binary_dilation(text, iterations=4))
    sizes = ndimage.sum(text, words, range(1, n + 1))
    return int(np.sum(np.asarray(sizes) >= 30))


def test_the_page_fits_its_content_and_names_it(tmp_path):
    """A robot cell's recording (tests/view/_cell.py) opened as its folder: the content's
    bounding box covers at least a quarter of the view, every frame's name is drawn, the
    sub-millimetre ellipsoids are drawn large enough to see."""
    from tests.view._cell import LABELS, record_cell

    path = record_cell(tmp_path / "rec")
    proc, info = view(str(tmp_path / "rec"))
    try:
        assert info["files"] == [path]
        assert (info["bodies"], info["arms"]) == (["box", "cup"], ["piper", "ur"])
        # two labels may touch (the world's and the UR's base are at one place)
        scene = screenshot(info["url"], tmp_path / "cell.png",
                           lambda img: content_share(img) >= 0.25
                           and label_count(img) >= len(LABELS) - 1
                           and ellipsoid_pixels(img) > ELLIPSOIDS)
    finally:
        proc.terminate()
        proc.wait(30)
    assert content_share(scene) >= 0.25, content_share(scene)
    assert label_count(scene) >= len(LABELS) - 1, label_count(scene)
    assert ellipsoid_pixels(scene) > ELLIPSOIDS, ellipsoid_pixels(scene)


def cell_page(tmp_path):
    from dqpose.record.reader import read
    from dqpose.view.page import Page
    from dqpose.view.timeline import timeline
    from tests.view._cell import record_cell

    return Page(timeline(read(record_cell(tmp_path))), port=0)


def test_each_arm_is_drawn_at_its_base(tmp_path):
    """The same path in each arm's base frame is drawn at each base (the World's
    configuration in the recording places them), with the arm's plan."""
    from tests.view._cell import BASES, PATH

    page = cell_page(tmp_path)
    try:
        ends = {}
        for arm, (q, t) in BASES.items():
            np.testing.assert_allclose(page.bases[arm].position, t, atol=1e-9)
            np.testing.assert_allclose(np.abs(page.bases[arm].wxyz), np.abs(q), atol=1e-9)
            assert page.paths[arm].name == f"/arms/{arm}/actual"
            assert page.plans[arm].name == f"/arms/{arm}/plan"
            ends[arm] = page.in_world(arm, PATH[-1])[0]
        # the PiPER faces the UR from 0.7 m: its path's end mirrored through (0, 0.35)
        np.testing.assert_allclose(ends["piper"], [-PATH[-1, 0], 0.7 - PATH[-1, 1], 0.2],
                                   atol=1e-9)
        np.testing.assert_allclose(ends["ur"], PATH[-1], atol=1e-9)
    finally:
        page.close()


def test_arms_without_a_configured_base_are_drawn_apart():
    from dqpose.view.page import Page
    from dqpose.view.timeline import Path, Timeline

    path = Path(np.array([0, 1], dtype=np.int64), np.array([[0.3, 0.0, 0.2], [0.4, 0.1, 0.2]]),
                np.array([[1.0, 0, 0, 0]] * 2))
    page = Page(Timeline(0, 1, {}, [], {"a": path, "b": path}), port=0)
    try:
        a, b = (np.asarray(page.bases[k].position) for k in "ab")
        np.testing.assert_allclose(a, [0, 0, 0])
        np.testing.assert_allclose(b, [0, -page.arm_spacing, 0])
        assert page.arm_spacing >= 1.5 * 0.1            # wider than the paths
        texts = [label.text for label in page.labels]
        assert "a base (not configured: the world frame)" in texts
        assert f"b base (not configured: drawn {page.arm_spacing:.2g} m aside)" in texts
    finally:
        page.close()


def test_the_ellipsoids_scale_is_chosen_shown_and_changed(tmp_path):
    from tests.view._cell import SIGMA

    page = cell_page(tmp_path)
    try:
        # 3-sigma half axes of about 1 mm in a cell of a metre: x100
        true = 3 * SIGMA
        assert page.scale_menu.value == "x100"
        assert "drawn **x100**" in page.legend.content
        np.testing.assert_allclose(page.ellipsoids["box"].scale, [100 * true] * 3, rtol=1e-6)
        page.scale_menu.value = "x1 (true size)"
        np.testing.assert_allclose(page.ellipsoids["box"].scale, [true] * 3, rtol=1e-6)
        assert "drawn **x1** (true size)" in page.legend.content
        page.show_labels.value = False
        assert not any(label.visible for label in page.labels)
    finally:
        page.close()


def test_bodies_leave_a_trail_of_their_last_seconds():
    from dqpose.view import layout
    from dqpose.view.page import Page
    from dqpose.view.timeline import Timeline, Track

    ns = np.arange(50, dtype=np.int64) * 100_000_000            # 0.1 s apart
    t = np.stack([np.linspace(0, 1, 50), np.zeros(50), np.zeros(50)], axis=1)
    track = Track(ns, t, np.array([[1.0, 0, 0, 0]] * 50), np.full((50, 6, 6), np.nan))
    page = Page(Timeline(0, int(ns[-1]), {"box": track}, []), port=0)
    try:
        first = int(round(49 - layout.TRAIL_SECONDS / 0.1))      # 2.9 s .. 4.9 s
        trail = page.trails["box"].points
        np.testing.assert_allclose(trail[0, 0], t[first], atol=1e-6)
        np.testing.assert_allclose(trail[-1, 1], t[49], atol=1e-6)
        assert len(trail) == 49 - first
        page.show(int(ns[0]))                           # one pose: no line to draw
        assert not page.trails["box"].visible
    finally:
        page.close()


def test_a_body_drawn_live_leaves_a_trail_of_its_last_seconds():
    """``--server`` and ``--live``: a pose arriving every 1/16 s; the trail is redrawn at most
    every TRAIL_PERIOD, through the positions of the last TRAIL_SECONDS of arrival."""
    import math

    from dqpose.view import layout
    from dqpose.view.page import TRAIL_PERIOD, Scene

    dt = 1 / 16                                 # exact in binary: no rounding at the period
    scene = Scene(port=0)
    now = [0.0]
    scene.clock = lambda: now[0]
    try:
        drawn = []
        for k in range(100):
            now[0] = dt * k
            scene.draw_live("box", (0.01 * k, 0.0, 0.0), (1.0, 0, 0, 0))
            line = scene.trails.get("box")
            if line is not None and (not drawn or line is not drawn[-1][1]):
                drawn.append((k, line))
        every = math.ceil(TRAIL_PERIOD / dt)
        assert [k for k, _ in drawn] == list(range(every, 100, every))
        k, line = drawn[-1]
        first = k - round(layout.TRAIL_SECONDS / dt)
        np.testing.assert_allclose(line.points[0, 0], [0.01 * first, 0, 0], atol=1e-6)
        np.testing.assert_allclose(line.points[-1, 1], [0.01 * k, 0, 0], atol=1e-6)
    finally:
        scene.close()
