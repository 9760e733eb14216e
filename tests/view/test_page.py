"""``dqpose view FILE.mcap`` in a real headless browser (Chromium from Debian's packages, software
WebGL): a recording of two fused bodies with large covariances and a plan, served by a real
``dqpose view`` process, rendered to a PNG; the ellipsoids' and the plan's colours cover enough
pixels, where the same page without bodies (rendered the same way) has none of them and is not
blank either."""
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
    call.measurements(tpb.ExecuteRequest(arm="ur"))
    for k, x in enumerate(xs):
        fb = tpb.ExecutionFeedback(time=0.1 * k, state=tpb.EXECUTION_WORKING)
        dq_to_pose(dq.from_pose([1.0, 0, 0, 0], [x, 0.3, 0.2]), fb.commanded)
        dq_to_pose(dq.from_pose([1.0, 0, 0, 0], [x, 0.32, 0.2]), fb.actual)
        call.fused(fb)
    call.end("OK")
    watch = recorder.call("dqpose.v1.Trajectories/WatchArm", tpb.GetArmRequest, tpb.ArmState)
    watch.measurements(tpb.GetArmRequest(arm="ur"))
    for _ in range(2):
        st = tpb.ArmState(arm="ur", state=tpb.EXECUTION_FINISHED)
        dq_to_pose(dq.from_pose([1.0, 0, 0, 0], [0.6, 0.32, 0.2]), st.pose)
        watch.fused(st)
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
