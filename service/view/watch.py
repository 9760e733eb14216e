"""``dqpose view --server HOST:PORT``: the page following a dqpose server through its own RPCs:
``World/Subscribe`` (every body's fused pose, drawn with its 3-sigma ellipsoid as it comes) and
``Trajectories/WatchArm`` for each of the server's arms (its tool where it is, and the path it
has followed since the page started), and the frame tree: ``ListFrames``' statics and sources,
each at its pose in its parent (a ``Lookup`` of it in its parent, made again for all every
:data:`TREE_REFRESH` rounds: fixed in its parent, it moves only when a configuration moves it),
listed again every :data:`TREE_PERIOD` s. A subscription gets every answer from the moment the
server took it, so a body's first fused pose is drawn too (the ``--live`` WebSocket sends a
channel's messages only once the viewer subscribed to a channel that its first message
advertised). Each stream runs in a thread of its own; the first that fails ends the page."""
from __future__ import annotations

import itertools
import threading
from collections import deque

import numpy as np

from dqpose import dq
from dqpose.events import say_err as say
from dqpose.record.views import ELLIPSOID_SIGMAS, ellipsoid_axes
from dqpose.view.page import Scene

#: WatchArm's rate: states a second per arm
ARM_HZ = 20.0
#: an arm's path keeps this many of its last positions (30 s at ARM_HZ)
PATH_POINTS = 600
#: the world's frames are listed again this often (s): a configuration may change, a static's
#: parent body come
TREE_PERIOD = 1.0
#: every this many rounds each fixed frame is looked up again (else only new ones)
TREE_REFRESH = 10


class Watcher:
    """Draws what the server at ``target`` streams on ``scene``; :meth:`start` its threads,
    :attr:`failed` set with :attr:`why` once a stream ends."""

    def __init__(self, target: str, scene: Scene, token: str | None = None):
        from dqpose.rpc.client import Client

        self.client = Client(target, token=token)
        self.target, self.scene = target, scene
        self.failed = threading.Event()
        self.why = ""

    def start(self) -> None:
        arms = [a.arm for a in self.client.list_arms()]
        say(event="following", server=self.target, arms=arms)
        self._thread(self.bodies, "world")
        self._thread(self.tree, "frames")
        for arm in arms:
            self._thread(self.arm, arm, arm)

    def _thread(self, fn, name: str, *args) -> None:
        def run() -> None:
            try:
                fn(*args)
                why = f"--server {self.target}: the {name} stream ended"
            except Exception as e:
                why = f"--server {self.target}: {e}"
            if not self.failed.is_set():
                self.why = why
                self.failed.set()
        threading.Thread(target=run, name=f"dqpose-view-{name}", daemon=True).start()

    def bodies(self) -> None:
        for a in self.client.subscribe():
            if a.fused is None:
                continue
            q, t = dq.to_pose(a.fused.mean)
            cov = np.asarray(a.fused.covariance, dtype=np.float64)
            half = axes = None
            if cov.shape == (6, 6) and np.all(np.isfinite(cov)):
                sigmas, axes = ellipsoid_axes(cov[3:, 3:])
                half = ELLIPSOID_SIGMAS * sigmas
            self.scene.draw_live(a.body, t, q, half, axes)
            if self.scene.reveal(("body", a.body, half is not None), t, half):
                say(event="drawn", body=a.body, ellipsoid=half is not None)

    def tree(self) -> None:
        """The frames fixed in their parents (``ListFrames``' statics and sources), each at
        ``T_parent_frame`` (a Lookup; one whose parent is not known yet, or a world not made
        yet, waits for the next round), drawn on the tree every :data:`TREE_PERIOD` s."""
        from dqpose.frames import FrameKind
        from dqpose.rpc.client import RpcError
        fixed: dict = {}
        for k in itertools.count():
            if self.failed.wait(TREE_PERIOD):
                return
            try:
                listed = self.client.frames()
            except RpcError:
                continue            # the world not made yet
            known, fixed = (fixed if k % TREE_REFRESH else {}), {}
            for f in listed:
                if f.kind not in (FrameKind.STATIC, FrameKind.SOURCE):
                    continue
                if f.name in known and known[f.name][0] == f.parent:
                    fixed[f.name] = known[f.name]
                    continue
                try:
                    fixed[f.name] = (f.parent, self.client.lookup(f.parent, f.name).pose)
                except RpcError:
                    pass            # its parent not known yet: the next round
            for name, T in self.scene.set_fixed(fixed).items():
                if self.scene.reveal(("fixed", name), dq.to_pose(T)[1], kind="frames"):
                    say(event="drawn", frame=name)

    def arm(self, arm: str) -> None:
        path: deque = deque(maxlen=PATH_POINTS)
        last = None
        for st in self.client.watch_arm(arm, rate_hz=ARM_HZ):
            # an arm at rest is not drawn again (each drawing is sent to the page)
            if st.pose is None or (last is not None and np.allclose(st.pose, last, rtol=0,
                                                                    atol=1e-9)):
                continue
            last = st.pose
            q, t = dq.to_pose(st.pose)
            if not path or np.linalg.norm(t - path[-1]) > 1e-6:
                path.append(t)
            self.scene.draw_arm(arm, np.array(path), t, q)
            self.scene.reveal(("base", arm), self.scene.arm_base(arm).position, kind="frames")
            at = self.scene.in_world(arm, t)[0]
            if self.scene.reveal(("arm", arm, len(path) > 1), at, kind="frames"):
                say(event="drawn", arm=arm, path=len(path) > 1)

    def close(self) -> None:
        self.client.close()
