"""The viewer draws the frame tree (issue 39): a recorded World configuration's statics and
sources, each at the pose its chain of parents gives (a table in the world and a mug on it, a
tool-centre offset and a camera riding on the fused body "tool", a camera on the ceiling, an
arm's base source), a line from each frame's parent to it; a frame whose parent is not known
yet hidden. In process (the scene's frames and segments) and in a real headless browser (the
tree's colour on the page)."""
from __future__ import annotations

import numpy as np
import pytest

from dqpose import dq

pytest.importorskip("viser", reason="the [view] extra (pip install -e '.[view]')")
pytest.importorskip("foxglove", reason="the [record] extra")

TABLE = dq.from_pose([np.cos(0.3), 0, 0, np.sin(0.3)], [0.8, -0.2, 0.0])
MUG = dq.from_pose([1, 0, 0, 0], [0.1, 0.05, 0.02])
TCP = dq.from_pose([1, 0, 0, 0], [0, 0, 0.12])
CAM = dq.from_pose([np.cos(0.2), np.sin(0.2), 0, 0], [0.05, 0, 0.03])
ROOM = dq.from_pose([0, 1, 0, 0], [0.5, 0, 1.5])
BASE = dq.from_pose([1, 0, 0, 0], [0.0, 0.4, 0.0])
#: the fused tool's path (world frame), one answer a step
TOOL = [dq.from_pose([np.cos(0.05 * k), 0, np.sin(0.05 * k), 0], [0.3 + 0.02 * k, 0.1, 0.4])
        for k in range(10)]


def record_tree(directory) -> str:
    from dqpose.record.recorder import Recorder
    from dqpose.rpc._proto.dqpose.v1 import fusion_pb2 as fpb
    from dqpose.rpc._proto.dqpose.v1 import world_pb2 as wpb
    from dqpose.rpc.geometry import dq_to_pose

    recorder = Recorder(directory)
    config = wpb.WorldConfig(
        statics=[wpb.StaticTransform(parent="", child="table", pose=dq_to_pose(TABLE)),
                 wpb.StaticTransform(parent="table", child="mug", pose=dq_to_pose(MUG)),
                 wpb.StaticTransform(parent="tool", child="tcp", pose=dq_to_pose(TCP))],
        sources=[fpb.Source(name="wrist", parent="tool", extrinsic=dq_to_pose(CAM)),
                 fpb.Source(name="ceiling", extrinsic=dq_to_pose(ROOM)),
                 fpb.Source(name="ur_flange", extrinsic=dq_to_pose(BASE))],
        arms=[wpb.ArmSource(arm="ur", source="ur_flange")])
    call = recorder.call("dqpose.v1.World/Configure", wpb.WorldConfig, wpb.WorldConfig)
    call.request(config)
    call.answer(config)
    call.end("OK")
    fuse = recorder.call("dqpose.v1.World/Subscribe", wpb.SubscribeRequest, fpb.FusedPose)
    cov = np.diag([1e-6] * 3 + [1e-8] * 3).ravel()
    for k, T in enumerate(TOOL):
        answer = fpb.FusedPose(body="tool", time=0.1 * k, covariance=cov)
        dq_to_pose(T, answer.pose)
        fuse.answer(answer)
    fuse.end("OK")
    recorder.close()
    (f,) = recorder.files
    return f


def position(T) -> np.ndarray:
    return dq.to_pose(T)[1]


def test_each_fixed_frame_is_drawn_where_its_chain_puts_it(tmp_path):
    from dqpose.record.reader import read
    from dqpose.view.page import Page
    from dqpose.view.timeline import timeline

    tl = timeline(read(record_tree(tmp_path)))
    page = Page(tl, port=0)
    try:
        tool = tl.tracks["tool"]
        assert sorted(page.fixed) == ["ceiling", "mug", "table", "tcp", "wrist"]  # not the base
        for k in (3, 9):
            page.show(int(tool.ns[k]))
            want = {"table": TABLE, "mug": dq.mul(TABLE, MUG), "tcp": dq.mul(TOOL[k], TCP),
                    "wrist": dq.mul(TOOL[k], CAM), "ceiling": ROOM}
            for name, T in want.items():
                f = page.fixed[name]
                assert f.visible, name
                np.testing.assert_allclose(f.position, position(T), atol=1e-9, err_msg=name)
                np.testing.assert_allclose(np.abs(np.dot(f.wxyz, dq.to_pose(T)[0])), 1.0,
                                           atol=1e-9, err_msg=name)
            # a link from each frame's parent: the world's to the tool, the table, the
            # ceiling and the arm's base; the table's to the mug; the tool's to tcp and wrist
            o = np.zeros(3)
            want_links = [(o, TOOL[k]), (o, TABLE), (o, ROOM), (o, BASE),
                          (TABLE, dq.mul(TABLE, MUG)), (TOOL[k], dq.mul(TOOL[k], TCP)),
                          (TOOL[k], dq.mul(TOOL[k], CAM))]
            np.testing.assert_allclose(
                sorted(map(tuple, np.asarray(page.tree.points, dtype=float).reshape(-1, 6))),
                sorted(tuple(np.concatenate([a if a is o else position(a), position(b)]))
                       for a, b in want_links), atol=1e-6)
        page.show(int(tool.ns[0]) - 1)      # the configuration in force, the tool not yet fused
        assert not page.fixed["tcp"].visible and not page.fixed["wrist"].visible
        assert page.fixed["mug"].visible and len(page.tree.points) == 4
    finally:
        page.close()


def test_a_chain_to_an_unknown_frame_or_round_a_loop_is_left_out():
    from dqpose.view.timeline import resolve

    frames = {"a": ("", TABLE), "b": ("a", MUG), "c": ("body", TCP), "d": ("e", CAM),
              "e": ("d", CAM)}
    got = resolve(frames, {})
    assert sorted(got) == ["a", "b"]
    np.testing.assert_allclose(got["b"], dq.mul(TABLE, MUG), atol=1e-12)
    got = resolve(frames, {"body": TOOL[2]})
    np.testing.assert_allclose(got["c"], dq.mul(TOOL[2], TCP), atol=1e-12)
    assert "d" not in got and "e" not in got


def tree_pixels(img: np.ndarray) -> int:
    """Pixels of the tree's yellow-green (green above red above blue) at any lightness; the
    green axis has red = blue, the grid and labels are grey, the other lines' hues differ."""
    from tests.view.test_page import SCENE_ROWS

    img = img[SCENE_ROWS]
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    return int(np.sum((g - r > 20) & (r - b > 20)))


#: pixels of the tree's links on the page, at the least (the empty page has none)
TREE = 300


def test_the_page_draws_the_tree_in_a_browser(tmp_path):
    from tests.view.test_page import CHROMIUM, drawn, screenshot, view

    if CHROMIUM is None:
        pytest.skip("no Chromium: apt-get install -y chromium (.ci/run installs it)")
    proc, info = view(record_tree(tmp_path / "rec"))
    try:
        scene = screenshot(info["url"], tmp_path / "tree.png",
                           lambda img: drawn(img) and tree_pixels(img) > TREE)
    finally:
        proc.terminate()
        proc.wait(30)
    assert drawn(scene)
    assert tree_pixels(scene) > TREE, tree_pixels(scene)
