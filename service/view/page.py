"""The viewer page (viser: a local web server with its own three.js client): the world frame, each
body's frame where it was last fused with its name and a trail of its last
:data:`~dqpose.view.layout.TRAIL_SECONDS`, its position's 3-sigma ellipsoid drawn in the body's
frame (the axes :func:`dqpose.record.views.ellipsoid_axes` gives Foxglove's ellipsoids too) at
the scale the page's menu says (x1, x10, x100: sub-millimetre ellipsoids are invisible at x1),
each arm at its own base (a plan's and an arm's poses are in the arm's base frame) with its
plans, its actual path and its tool's frame, the frame tree (a line from each frame's parent to
it; a World's statics and sources drawn as frames of their own, riding on their parents), and,
for a file, a time slider (the scene as it was at that time). The camera, the grid and the
frames' axes fit what is drawn (:mod:`dqpose.view.layout`); the controls are docked beside the
view, never over it."""
from __future__ import annotations

import itertools
import threading
import time
from collections import deque

import numpy as np
import viser

from dqpose import dq
from dqpose.record.views import ELLIPSOID_SIGMAS, ellipsoid_axes
from dqpose.view import layout
from dqpose.view.guard import protect
from dqpose.view.timeline import Timeline, resolve, tree

#: the ellipsoids' colour (RGB), which nothing else on the page has
ELLIPSOID_RGB = (220, 30, 200)
ELLIPSOID_OPACITY = 0.6
PLAN_RGB = (255, 140, 0)
#: an arm's actual path (green and blue above red: neither the plans' nor the ellipsoids')
ACTUAL_RGB = (0, 190, 230)
#: a body's trail (blue above red = green: neither the ellipsoids' nor the plans')
TRAIL_RGB = (70, 70, 170)
#: the frame tree's links (green above red above blue: none of the other lines', nor the
#: green axis's, whose red and blue are equal)
TREE_RGB = (120, 190, 0)
#: lines' width in pixels, whatever the content's size
LINE_PX = 3.0
TRAIL_PX = 2.0
#: Trajectories/Plan's recorded plan, in the world frame (service/rpc/trajectories.py); every
#: other plan is named after the arm that ran it, in that arm's base frame
WORLD_PLAN = "Plan"
#: how far apart (m) arms whose base the page does not know are drawn, by default
ARM_SPACING = 1.0
#: the positions a body drawn live keeps for its trail, at the most, and how often (s) its trail
#: is redrawn at the most
LIVE_TRAIL = 600
TRAIL_PERIOD = 0.1
#: the points a line is drawn through, at the most (a slider's move redraws every line)
MAX_LINE_POINTS = 2000
SCALE_LABELS = {s: f"x{s}" + (" (true size)" if s == 1 else "") for s in layout.SCALES}


def _segments(p: np.ndarray) -> np.ndarray:
    return np.stack([p[:-1], p[1:]], axis=1)


class Scene:
    """The page's drawing: the grid, the world frame, a frame, a label, a trail and an ellipsoid
    per body (made when a body first comes), each arm's base frame with its plan, path and
    tool, the world's plans. Drawn from any thread (one lock)."""

    def __init__(self, host: str = "127.0.0.1", port: int = 8080):
        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        protect(self.server, host)
        self.port = self.server.get_port()
        self.lock = threading.RLock()
        gui = self.server.gui
        gui.configure_theme(show_share_button=False, show_logo=False)
        gui.main_panel.dock_right()
        self.view = layout.camera(())
        self._fitted: tuple | None = None      # the box the cameras were last moved to
        self.scale, self._scale_chosen = 1, False
        self.frames: dict = {}
        self.labels: list = []
        self.ellipsoids: dict = {}
        self.half: dict = {}        # body -> its ellipsoid's true half axes (m), their rotation
        self.trails: dict = {}
        self.plans: dict = {}
        self.bases: dict = {}       # arm -> its base's frame
        self.placed: dict = {}      # arm -> the k of layout.aside (None: its base is known)
        self.arm_spacing = ARM_SPACING
        self.paths: dict = {}       # arm -> its actual path's line
        self.tools: dict = {}       # arm -> its tool's frame
        self.fixed: dict = {}       # a static's or source's name -> its frame
        self.tree: viser.LineSegmentsHandle | None = None     # the tree's links
        # drawn live: the fixed frames (name -> (parent, T_parent_frame)), each body's last
        # pose, when the tree was last drawn
        self.live_fixed: dict = {}
        self._now: dict = {}
        self._treed = -TRAIL_PERIOD
        self._past: dict = {}       # body -> (arrival, position) drawn live, for its trail
        self._trailed: dict = {}    # body -> when its trail was last drawn live
        self.clock = time.monotonic     # of a live pose's arrival
        self._places: dict = {}     # what was drawn live -> (its kind for fit, first place)
        self._largest: float | None = None
        self.scale_menu = gui.add_dropdown("ellipsoids", tuple(SCALE_LABELS.values()),
                                           initial_value=SCALE_LABELS[1])
        self.scale_menu.on_update(self._scale_picked)
        self.show_labels = gui.add_checkbox("names", initial_value=True)
        self.show_labels.on_update(lambda _: self._relabel())
        self.show_tree = gui.add_checkbox("tree", initial_value=True)
        self.show_tree.on_update(lambda _: self._retree())
        self.legend = gui.add_markdown("")
        self.world = self._frame("/world", "world", self.view.axes * 1.5)
        self._grid()

    def _frame(self, name: str, text: str, axes: float | None = None, visible: bool = True,
               anchor="bottom-left"):
        """A frame at ``name`` with its label ``text`` beside its origin (on the side
        ``anchor`` says: an arm's base is below, where the world frame may be too)."""
        axes = self.view.axes if axes is None else axes
        frame = self.server.scene.add_frame(name, axes_length=axes, axes_radius=axes / 25,
                                            visible=visible)
        self.labels.append(self.server.scene.add_label(
            f"{name}/label", text, anchor=anchor, font_screen_scale=1.3,
            visible=self.show_labels.value))
        return frame

    def _grid(self) -> None:
        """The grid under what the view frames, 3 times its size (at ``view.floor``)."""
        step = layout.grid_step(self.view.extent)
        section = 10 * step
        size = section * np.ceil(3 * self.view.extent / section)
        centre = np.round(self.view.look_at[:2] / section) * section
        self.server.scene.add_grid("/grid", width=size, height=size, cell_size=step,
                                   section_size=section,
                                   position=(*centre, self.view.floor))
        self._legend()

    def _legend(self) -> None:
        step = layout.grid_step(self.view.extent)
        self.legend.content = (
            f"**ellipsoids** (magenta): 3σ of each body's position, drawn "
            f"**x{self.scale}**{' (true size)' if self.scale == 1 else ''}  \n"
            f"**trails** (indigo): each body's last {layout.TRAIL_SECONDS:g} s  \n"
            f"**plans** orange, **arms' actual paths** cyan, each arm at its base  \n"
            f"**tree** (yellow-green): each frame's link from its parent  \n"
            f"**grid**: {_length(step)} cells at the world's z = "
            f"{0 if self.view.floor == 0 else _length(self.view.floor)}")

    def _scale_picked(self, event) -> None:
        if event.client is not None:        # a person chose it: no longer chosen for them
            self._scale_chosen = True
        with self.lock:
            self.scale = next(s for s, text in SCALE_LABELS.items()
                              if text == self.scale_menu.value)
            for body in self.half:
                self._ellipsoid(body)
            self._legend()

    def _relabel(self) -> None:
        for label in self.labels:
            label.visible = self.show_labels.value

    def _retree(self) -> None:
        with self.lock:
            if self.tree is not None:
                self.tree.visible = self.show_tree.value

    def draw_tree(self, links: dict, fixed=()) -> None:
        """The frame tree: a line from each frame's parent to it (``links``: name ->
        ``(parent, T_world_name (8,))``, ``None`` where it is not known now; the world ``""``
        at the origin) and the frame of each of ``fixed`` (statics and sources) with its name,
        hidden while its pose is not known."""
        with self.lock:
            at = {"": np.zeros(3)} | {n: dq.to_pose(T)[1] for n, (_, T) in links.items()
                                      if T is not None}
            for name in fixed:
                if name not in self.fixed:
                    self.fixed[name] = self._frame(f"/fixed/{name}", name, visible=False)
            for name, frame in self.fixed.items():
                T = links.get(name, (None, None))[1] if name in fixed else None
                if T is None:
                    frame.visible = False
                else:
                    q, t = dq.to_pose(T)
                    frame.position, frame.wxyz, frame.visible = tuple(t), tuple(q), True
            segments = [(at[p], at[n]) for n, (p, T) in links.items() if T is not None
                        and p in at]
            if segments:            # the same name: the tree is replaced
                self.tree = self.server.scene.add_line_segments(
                    "/tree", np.array(segments), TREE_RGB, thickness=LINE_PX,
                    thickness_units="screen", visible=self.show_tree.value)
            elif self.tree is not None:
                self.tree.visible = False

    def body(self, body: str):
        """The frame and the ellipsoid of ``body`` (hidden until drawn)."""
        with self.lock:
            if body not in self.frames:
                self.frames[body] = self._frame(f"/world/{body}", body, visible=False)
                self.ellipsoids[body] = self.server.scene.add_icosphere(
                    f"/world/{body}/ellipsoid", radius=1.0, color=ELLIPSOID_RGB,
                    subdivisions=3, opacity=ELLIPSOID_OPACITY, visible=False)
            return self.frames[body], self.ellipsoids[body]

    def _ellipsoid(self, body: str) -> None:
        half, _ = self.half[body]
        ell = self.ellipsoids[body]
        ell.scale = tuple(np.maximum(self.scale * np.asarray(half), 1e-9).tolist())

    def draw_body(self, body: str, t, q, half_axes=None, axes_q=None, trail=None) -> None:
        """``body`` at ``t``, ``q``, its ellipsoid's half axes along the rotation ``axes_q``
        (in the body's frame; ``None``: no ellipsoid), its trail through ``trail (n, 3)``
        (``None``: as it was)."""
        with self.lock:
            frame, ell = self.body(body)
            frame.position, frame.wxyz, frame.visible = tuple(t), tuple(q), True
            if half_axes is None:
                self.half.pop(body, None)
                ell.visible = False
            else:
                self.half[body] = (tuple(np.asarray(half_axes, dtype=float)), tuple(axes_q))
                ell.wxyz = tuple(axes_q)
                self._ellipsoid(body)
                ell.visible = True
            if trail is not None:
                self._line(self.trails, body, f"/trails/{body}", trail, TRAIL_RGB, TRAIL_PX)

    def hide_body(self, body: str) -> None:
        with self.lock:
            frame, ell = self.body(body)
            frame.visible = ell.visible = False
            self.half.pop(body, None)
            self._line(self.trails, body, f"/trails/{body}", None, TRAIL_RGB, TRAIL_PX)

    def _line(self, lines: dict, key: str, name: str, positions, rgb, px: float) -> None:
        """The line ``name`` through ``positions (n, 3)`` (``None`` or fewer than 2: hidden)."""
        p = None if positions is None else np.asarray(positions, dtype=float).reshape(-1, 3)
        if p is not None and len(p) > MAX_LINE_POINTS:      # evenly, the last one kept
            p = p[np.linspace(0, len(p) - 1, MAX_LINE_POINTS).round().astype(int)]
        if p is not None and len(p) > 1:      # the same name: the line is replaced
            lines[key] = self.server.scene.add_line_segments(
                name, _segments(p), rgb, thickness=px, thickness_units="screen")
        elif key in lines:
            lines[key].visible = False

    def arm_base(self, arm: str, pose=None):
        """The frame of ``arm``'s base, at ``pose`` (``T_world_base``, ``(8,)``) or, when the
        page does not know it, :func:`~dqpose.view.layout.aside` the others (said on its
        label); what the arm's path, tool and plans are drawn in."""
        with self.lock:
            if arm not in self.bases:
                if pose is None:
                    k = sum(1 for v in self.placed.values() if v is not None)
                    k += any(v is None for v in self.placed.values())
                    self.placed[arm] = k
                    where = layout.aside(k, self.arm_spacing)
                    # the server's rule for an arm the World does not place: its base is
                    # the world frame (trajectories.proto); a second one is moved aside
                    text = f"{arm} base (not configured: " + (
                        f"drawn {abs(where[1]):.2g} m aside)" if k else "the world frame)")
                    self.bases[arm] = self._frame(f"/arms/{arm}", text, anchor="top-left")
                    self.bases[arm].position = tuple(where)
                else:
                    self.placed[arm] = None
                    self.bases[arm] = self._frame(f"/arms/{arm}", f"{arm} base",
                                                  anchor="top-left")
            if pose is not None and self.placed[arm] is None:
                q, t = dq.to_pose(np.asarray(pose, dtype=float))
                self.bases[arm].position, self.bases[arm].wxyz = tuple(t), tuple(q)
            return self.bases[arm]

    def draw_plan(self, name: str, positions) -> None:
        """The plan ``name`` through ``positions (n, 3)`` (``None`` or fewer than 2: hidden):
        Trajectories/Plan's in the world frame, an arm's in its base frame."""
        with self.lock:
            if name == WORLD_PLAN:
                self._line(self.plans, name, f"/plans/{name}", positions, PLAN_RGB, LINE_PX)
            else:
                self.arm_base(name)
                self._line(self.plans, name, f"/arms/{name}/plan", positions, PLAN_RGB,
                           LINE_PX)

    def draw_arm(self, arm: str, positions, t=None, q=None) -> None:
        """The actual path of ``arm`` through ``positions (n, 3)`` and its tool's frame at
        ``t``, ``q`` (``None``: hidden), in its base frame."""
        with self.lock:
            self.arm_base(arm)
            self._line(self.paths, arm, f"/arms/{arm}/actual", positions, ACTUAL_RGB, LINE_PX)
            if arm not in self.tools:
                self.tools[arm] = self._frame(f"/arms/{arm}/tool", f"{arm} tool",
                                              visible=False)
            tool = self.tools[arm]
            if t is None:
                tool.visible = False
            else:
                tool.position, tool.wxyz, tool.visible = tuple(t), tuple(q), True

    def draw_live(self, body: str, t, q, half_axes=None, axes_q=None) -> None:
        """``body`` drawn as it comes (``--server``, ``--live``), its trail through its
        positions of the last :data:`~dqpose.view.layout.TRAIL_SECONDS` of arrival (at most
        :data:`LIVE_TRAIL` of them), redrawn every :data:`TRAIL_PERIOD` at most (a trail is
        sent whole: at every pose, 20 bodies at 30 Hz would send the page ~8 MB/s)."""
        now = self.clock()
        with self.lock:
            past = self._past.setdefault(body, deque(maxlen=LIVE_TRAIL))
            past.append((now, tuple(t)))
            trail = None
            if now - self._trailed.get(body, -TRAIL_PERIOD) >= TRAIL_PERIOD:
                self._trailed[body] = now
                times = [a for a, _ in past]
                trail = [p for _, p in itertools.islice(past, layout.recent(times, now), None)]
            self.draw_body(body, t, q, half_axes, axes_q, trail)
            self._now[body] = dq.from_pose(np.asarray(q, dtype=float),
                                           np.asarray(t, dtype=float))
            if now - self._treed >= TRAIL_PERIOD:       # as often as a trail at most
                self._treed = now
                self.draw_tree(*tree(self.live_fixed, frozenset(), self._now))

    def set_fixed(self, frames: dict) -> dict:
        """The frames fixed in their parents drawn live from now on (name -> ``(parent,
        T_parent_frame)``: ``/tf_static``'s), the tree drawn again; ``T_world_frame`` of
        those whose chain is known now."""
        with self.lock:
            self.live_fixed = dict(frames)
            self.draw_tree(*tree(self.live_fixed, frozenset(), self._now))
            return resolve(self.live_fixed, self._now)

    def reveal(self, key, at, half_axes=None, kind: str = "bodies") -> bool:
        """Whether ``key`` is drawn for the first time; if so the camera is fitted again to the
        first places (``at``, world frame) of everything drawn so far, each of a ``kind`` of
        :meth:`fit` (``"lines"``, ``"frames"``, ``"bodies"``), and to the largest ellipsoid
        seen (``half_axes``)."""
        with self.lock:
            if half_axes is not None:
                self._largest = max(self._largest or 0.0, float(np.max(half_axes)))
            if key in self._places:
                return False
            self._places[key] = (kind, np.asarray(at, dtype=float))
            seen: dict[str, list] = {"lines": [], "frames": [], "bodies": []}
            for k, place in self._places.values():
                seen[k].append(place)
            self.fit(**seen, largest_half_axis=self._largest)
            return True

    def in_world(self, arm: str, points) -> np.ndarray:
        """``points (n, 3)`` of ``arm``'s base frame in the world, where its base is drawn."""
        base = self.arm_base(arm)
        pose = dq.from_pose(np.asarray(base.wxyz, dtype=float),
                            np.asarray(base.position, dtype=float))
        return dq.transform(pose, np.asarray(points, dtype=float).reshape(-1, 3))

    def fit(self, lines=(), frames=(), bodies=(), largest_half_axis: float | None = None) -> None:
        """The camera, the grid and the frames' axes fitted to what is drawn (world frame; each
        a list of arrays of points, ``(n, 3)`` or ``(3,)``): the points of ``lines``, the
        origins of ``frames`` with their axes, the positions of ``bodies`` with their axes and
        their ellipsoids of true half axes up to ``largest_half_axis`` (m); the ellipsoids'
        scale chosen for them unless a person chose one. The page's cameras move only when the
        content left the box they were last fitted to; the camera a page opened later starts
        with is always the new one."""
        parts = [_stack(x) for x in (lines, frames, bodies)]
        p = np.concatenate(parts)
        with self.lock:
            lo, hi = layout.box(p)
            extent = float(np.max(hi - lo))
            if not self._scale_chosen:
                scale = layout.ellipsoid_scale(largest_half_axis, extent)
                # assignable (GuiInputHandle's setter), though viser's dropdown types it not
                self.scale_menu.value = SCALE_LABELS[scale]  # type: ignore[misc]
            axes = layout.AXES_SHARE * extent
            pad = np.concatenate([np.zeros(len(parts[0])), np.full(len(parts[1]), axes),
                                  np.full(len(parts[2]), max(
                                      axes, self.scale * (largest_half_axis or 0.0)))])
            self.view = v = layout.camera(p, pad)
            lo, hi = layout.box(p, pad)
            cam = self.server.initial_camera
            cam.fov, cam.near, cam.far = layout.FOV, v.near, v.far
            cam.look_at, cam.position = tuple(v.look_at), tuple(v.position)
            old = self._fitted
            if old is None or np.any(lo < old[0]) or np.any(hi > old[1]):
                self._fitted = (lo, hi)
                for client in self.server.get_clients().values():
                    c = client.camera
                    c.fov, c.near, c.far = layout.FOV, v.near, v.far
                    c.look_at, c.position = tuple(v.look_at), tuple(v.position)
            for frame in (*self.frames.values(), *self.bases.values(), *self.tools.values(),
                          *self.fixed.values()):
                frame.axes_length, frame.axes_radius = v.axes, v.axes / 25
            self.world.axes_length, self.world.axes_radius = 1.5 * v.axes, v.axes / 20
            self._grid()

    def close(self) -> None:
        self.server.stop()


def _stack(parts) -> np.ndarray:
    arrays = [np.asarray(a, dtype=float).reshape(-1, 3) for a in parts]
    return np.concatenate(arrays) if arrays else np.zeros((0, 3))


def _length(m: float) -> str:
    """``m`` metres to 3 digits in the unit that reads best (mm below 1 cm, cm below 1 m)."""
    for unit, size in (("m", 1.0), ("cm", 1e-2), ("mm", 1e-3)):
        if abs(m) >= size * 0.999:
            return f"{m / size:.3g} {unit}"
    return f"{m * 1e3:.3g} mm"


def largest_half_axis(covariances) -> float | None:
    """The median over poses of each pose's largest 3-sigma half axis of position (m), from
    covariances ``(n, 6, 6)`` (NaN ones left out): what the page sizes ellipsoids for."""
    c = np.asarray(covariances, dtype=np.float64).reshape(-1, 6, 6)
    c = c[np.all(np.isfinite(c), axis=(1, 2))]
    if not len(c):
        return None
    top = np.linalg.eigvalsh(c[:, 3:, 3:])[:, -1]
    return float(ELLIPSOID_SIGMAS * np.sqrt(np.median(np.clip(top, 0.0, None))))


class Page(Scene):
    """Serves ``tl`` on ``host:port`` (viser takes the next free port when that one is taken:
    :attr:`port` is the one it serves on), with a time slider, the camera fitted to everything
    the file holds."""

    def __init__(self, tl: Timeline, host: str = "127.0.0.1", port: int = 8080):
        super().__init__(host, port)
        self.tl = tl
        for b in tl.tracks:
            self.body(b)
        self.plan_names = sorted({name for name, _, _ in tl.plans})
        arms = sorted(set(tl.arms) | {n for n in self.plan_names if n != WORLD_PLAN})
        self.arm_spacing = _spacing([a.t for a in tl.arms.values()]
                                    + [p for n, _, p in tl.plans if n != WORLD_PLAN])
        for arm in sorted(arms, key=lambda a: a not in tl.bases):   # the known ones first
            self.arm_base(arm, tl.bases[arm].at(tl.end) if arm in tl.bases else None)
        duration = max((tl.end - tl.start) * 1e-9, 1e-3)
        self.slider = self.server.gui.add_slider(
            "time (s)", min=0.0, max=duration, step=min(1e-3, duration / 100),
            initial_value=duration, order=-1.0)
        tracks = list(tl.tracks.values())
        self.fit(*self._content(), [t.t for t in tracks],
                 largest_half_axis(np.concatenate([t.cov for t in tracks])) if tracks else None)
        self.slider.on_update(lambda _: self.show(self.ns(self.slider.value)))
        self.show(tl.end)

    def _content(self) -> tuple[list, list]:
        """Where the file draws plans (``lines``), and arms' bases and tools (``frames``) in
        the world frame (:meth:`fit`)."""
        tl = self.tl
        lines = [p if n == WORLD_PLAN else self.in_world(n, p) for n, _, p in tl.plans]
        frames = [self.in_world(arm, path.t) for arm, path in tl.arms.items()]
        frames += [np.asarray(b.position, dtype=float)[None] for b in self.bases.values()]
        last = {b: dq.from_pose(t.q[-1], t.t[-1]) for b, t in tl.tracks.items()}
        links, fixed = self.tree_at(tl.end, last)
        frames += [dq.to_pose(links[n][1])[1][None] for n in fixed if links[n][1] is not None]
        return lines, frames

    def tree_at(self, ns: int, known: dict) -> tuple[dict, list]:
        """The tree at ``ns`` (:meth:`draw_tree`'s arguments): each body of ``known`` (name ->
        ``T_world_body``, those drawn now) linked from the world, each static and source from
        its parent, at the pose its chain gives (:func:`~dqpose.view.timeline.resolve`); the
        statics and the sources that are no arm's base drawn as frames."""
        fx = self.tl.fixed
        if fx is None:
            return tree({}, frozenset(), known)
        k = fx.at(ns)
        return tree(fx.frames[k], fx.bases[k], known)

    def ns(self, seconds: float) -> int:
        return self.tl.start + int(round(seconds * 1e9))

    def show(self, ns: int) -> None:
        """The scene as it was at ``ns``."""
        with self.lock:
            known = {}
            for body, track in self.tl.tracks.items():
                i = track.at(ns)
                if i is None:
                    self.hide_body(body)
                    continue
                known[body] = dq.from_pose(track.q[i], track.t[i])
                trail = track.t[layout.recent(track.ns * 1e-9, ns * 1e-9):i + 1]
                cov = track.cov[i]
                if np.all(np.isfinite(cov)):
                    sigmas, q = ellipsoid_axes(cov[3:, 3:])
                    self.draw_body(body, track.t[i], track.q[i], ELLIPSOID_SIGMAS * sigmas, q,
                                   trail)
                else:
                    self.draw_body(body, track.t[i], track.q[i], trail=trail)
            for arm, bases in self.tl.bases.items():
                self.arm_base(arm, bases.at(ns))
            self.draw_tree(*self.tree_at(ns, known))
            for name in self.plan_names:
                self.draw_plan(name, self.tl.plan_at(name, ns))
            for arm, path in self.tl.arms.items():
                n = path.upto(ns)
                if n:
                    self.draw_arm(arm, path.t[:n], path.t[n - 1], path.q[n - 1])
                else:
                    self.draw_arm(arm, ())


def _spacing(paths) -> float:
    """How far apart to draw arms whose base is unknown: 1.5 times the widest of their paths
    and plans (in their base frames) along y, at least 0.3 m."""
    widths = [float(np.ptp(np.asarray(p)[:, 1])) for p in paths if len(p)]
    return max(0.3, 1.5 * max(widths)) if widths else ARM_SPACING
