"""The viewer page (viser: a local web server with its own three.js client): the world frame, each
body's frame where it was last fused, its position's 3-sigma ellipsoid drawn in the body's frame
(the axes :func:`dqpose.record.views.ellipsoid_axes` gives Foxglove's ellipsoids too), the plans
as lines, each arm's actual path as a line of another colour with its tool's frame where it
last was (a plan's and an arm's poses are in the arm's base frame, drawn as the world frame),
and a time slider over the recording (the scene as it was at that time)."""
from __future__ import annotations

import numpy as np
import viser

from dqpose.record.views import ELLIPSOID_SIGMAS, ellipsoid_axes
from dqpose.view.timeline import Timeline

#: the ellipsoids' colour (RGB), which nothing else on the page has
ELLIPSOID_RGB = (220, 30, 200)
ELLIPSOID_OPACITY = 0.6
PLAN_RGB = (255, 140, 0)
#: an arm's actual path (green and blue above red: neither the plans' nor the ellipsoids')
ACTUAL_RGB = (0, 190, 230)
AXES = 0.1      # m, a body frame's axes
#: where the camera starts, from the centre of the bodies' and plans' last positions (m)
CAMERA = np.array([1.2, -1.2, 0.9])


class Scene:
    """The page's drawing: the grid, the world frame, a frame and an ellipsoid per body (made
    when a body first comes), a line per plan."""

    def __init__(self, host: str = "127.0.0.1", port: int = 8080):
        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.port = self.server.get_port()
        self.server.scene.add_grid("/grid", width=4.0, height=4.0, cell_size=0.1,
                                   section_size=1.0)
        self.server.scene.add_frame("/world", axes_length=0.3, axes_radius=0.008)
        self.frames: dict = {}
        self.ellipsoids: dict = {}
        self.plans: dict = {}
        self.paths: dict = {}       # arm -> its actual path's line
        self.tools: dict = {}       # arm -> its tool's frame

    def body(self, body: str):
        """The frame and the ellipsoid of ``body`` (hidden until drawn)."""
        if body not in self.frames:
            scene = self.server.scene
            self.frames[body] = scene.add_frame(f"/world/{body}", axes_length=AXES,
                                                axes_radius=0.004, visible=False)
            self.ellipsoids[body] = scene.add_icosphere(
                f"/world/{body}/ellipsoid", radius=1.0, color=ELLIPSOID_RGB, subdivisions=3,
                opacity=ELLIPSOID_OPACITY, visible=False)
        return self.frames[body], self.ellipsoids[body]

    def draw_body(self, body: str, t, q, half_axes=None, axes_q=None) -> None:
        """``body`` at ``t``, ``q``, its ellipsoid's half axes along the rotation ``axes_q``
        (in the body's frame; ``None``: no ellipsoid)."""
        frame, ell = self.body(body)
        frame.position, frame.wxyz, frame.visible = tuple(t), tuple(q), True
        if half_axes is None:
            ell.visible = False
        else:
            ell.wxyz = tuple(axes_q)
            ell.scale = tuple(np.maximum(np.asarray(half_axes, dtype=float), 1e-6).tolist())
            ell.visible = True

    def hide_body(self, body: str) -> None:
        frame, ell = self.body(body)
        frame.visible = ell.visible = False

    def draw_plan(self, name: str, positions) -> None:
        """The path through ``positions (n, 3)`` (``None`` or fewer than 2: hidden)."""
        p = None if positions is None else np.asarray(positions, dtype=float)
        if p is not None and len(p) > 1:      # the same name: the line is replaced
            self.plans[name] = self.server.scene.add_line_segments(
                f"/plans/{name}", np.stack([p[:-1], p[1:]], axis=1), PLAN_RGB,
                thickness=0.01)
        elif name in self.plans:
            self.plans[name].visible = False

    def draw_arm(self, arm: str, positions, t=None, q=None) -> None:
        """The actual path of ``arm`` through ``positions (n, 3)`` and its tool's frame at
        ``t``, ``q`` (``None``: hidden)."""
        p = np.asarray(positions, dtype=float).reshape(-1, 3)
        if len(p) > 1:
            self.paths[arm] = self.server.scene.add_line_segments(
                f"/arms/{arm}/actual", np.stack([p[:-1], p[1:]], axis=1), ACTUAL_RGB,
                thickness=0.01)
        elif arm in self.paths:
            self.paths[arm].visible = False
        if arm not in self.tools:
            self.tools[arm] = self.server.scene.add_frame(
                f"/arms/{arm}/tool", axes_length=AXES, axes_radius=0.004, visible=False)
        tool = self.tools[arm]
        if t is None:
            tool.visible = False
        else:
            tool.position, tool.wxyz, tool.visible = tuple(t), tuple(q), True

    def look_at(self, points) -> None:
        """The camera on ``points``' centre, from above one side."""
        if len(points):
            centre = np.mean(np.asarray(points, dtype=float), axis=0)
            self.server.initial_camera.look_at = tuple(centre.tolist())
            self.server.initial_camera.position = tuple((centre + CAMERA).tolist())

    def close(self) -> None:
        self.server.stop()


class Page(Scene):
    """Serves ``tl`` on ``host:port`` (viser takes the next free port when that one is taken:
    :attr:`port` is the one it serves on), with a time slider."""

    def __init__(self, tl: Timeline, host: str = "127.0.0.1", port: int = 8080):
        super().__init__(host, port)
        self.tl = tl
        for b in tl.tracks:
            self.body(b)
        self.plan_names = sorted({name for name, _, _ in tl.plans})
        duration = max((tl.end - tl.start) * 1e-9, 1e-3)
        self.slider = self.server.gui.add_slider(
            "time (s)", min=0.0, max=duration, step=min(1e-3, duration / 100),
            initial_value=duration)
        self.look_at([t.t[-1] for t in tl.tracks.values()]
                     + [a.t[-1] for a in tl.arms.values()]
                     + [p[-1] for _, _, p in tl.plans if len(p)])
        self.slider.on_update(lambda _: self.show(self.ns(self.slider.value)))
        self.show(tl.end)

    def ns(self, seconds: float) -> int:
        return self.tl.start + int(round(seconds * 1e9))

    def show(self, ns: int) -> None:
        """The scene as it was at ``ns``."""
        for body, track in self.tl.tracks.items():
            i = track.at(ns)
            if i is None:
                self.hide_body(body)
                continue
            cov = track.cov[i]
            if np.all(np.isfinite(cov)):
                sigmas, q = ellipsoid_axes(cov[3:, 3:])
                self.draw_body(body, track.t[i], track.q[i], ELLIPSOID_SIGMAS * sigmas, q)
            else:
                self.draw_body(body, track.t[i], track.q[i])
        for name in self.plan_names:
            self.draw_plan(name, self.tl.plan_at(name, ns))
        for arm, path in self.tl.arms.items():
            n = path.upto(ns)
            if n:
                self.draw_arm(arm, path.t[:n], path.t[n - 1], path.q[n - 1])
            else:
                self.draw_arm(arm, ())
