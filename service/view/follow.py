"""``dqpose view --live HOST:PORT``: the page following a server live, as a client of its
``serve --live`` WebSocket (Foxglove's protocol, ``foxglove.sdk.v1``): it subscribes to ``/tf``
(the bodies' frames), ``/tf_static`` (a World's statics and sources, the frame tree; latched: its
last message comes first), ``/fused/ellipsoids`` (each body's 3-sigma ellipsoid, drawn as the
recording draws it) and ``/plans/*``, and draws each message as it comes. A channel's messages
logged before the subscription reached the server are not sent (the protocol keeps none)."""
from __future__ import annotations

import json
import struct

from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.PosesInFrame_pb2 import PosesInFrame
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from websockets.sync.client import connect
from websockets.typing import Subprotocol

from dqpose import dq
from dqpose.events import say_err as say
from dqpose.record.topics import ELLIPSOIDS_TOPIC, TF_STATIC_TOPIC, TF_TOPIC, plan_topic
from dqpose.record.views import WORLD
from dqpose.view.page import WORLD_PLAN, Scene

SUBPROTOCOL = "foxglove.sdk.v1"
MESSAGE_DATA = 0x01
PLANS = plan_topic("")


def _q(r) -> tuple:
    return (r.w, r.x, r.y, r.z)


class Follower:
    """Draws what the live server at ``url`` sends on ``scene`` until the connection ends."""

    def __init__(self, url: str, scene: Scene):
        self.url, self.scene = url, scene
        self.subscriptions: dict[int, str] = {}      # subscription id -> topic
        self.ellipsoids: dict[str, tuple] = {}       # body -> (half axes, their rotation)
        self.poses: dict[str, tuple] = {}            # body -> (t, q), the last

    def run(self) -> None:
        with connect(self.url, subprotocols=[Subprotocol(SUBPROTOCOL)], open_timeout=30,
                     max_size=None) as ws:
            for m in ws:
                if isinstance(m, str):
                    self.operation(ws, json.loads(m))
                elif m[0] == MESSAGE_DATA:
                    sub, _ = struct.unpack_from("<IQ", m, 1)
                    topic = self.subscriptions.get(sub)
                    if topic is not None:
                        self.draw(topic, bytes(m[13:]))

    def operation(self, ws, op: dict) -> None:
        if op.get("op") != "advertise":
            return
        subs = []
        for ch in op["channels"]:
            topic = ch["topic"]
            if topic in (TF_TOPIC, TF_STATIC_TOPIC, ELLIPSOIDS_TOPIC) or \
                    topic.startswith(PLANS):
                sub = len(self.subscriptions) + 1
                self.subscriptions[sub] = topic
                subs.append({"id": sub, "channelId": ch["id"]})
        if subs:
            ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
            say(event="following", topics=[self.subscriptions[s["id"]] for s in subs])

    def draw_body(self, body: str) -> None:
        """``body`` where ``/tf`` last put it, with the last ellipsoid it came with (a pose's
        ``/tf`` comes before its ellipsoid: both redraw)."""
        if body in self.poses:
            t, q = self.poses[body]
            half, axes = self.ellipsoids.get(body, (None, None))
            self.scene.draw_live(body, t, q, half, axes)
            # a body's first drawing (with an ellipsoid)
            if self.scene.reveal(("body", body, half is not None), t, half):
                say(event="drawn", body=body, ellipsoid=half is not None)

    def draw(self, topic: str, data: bytes) -> None:
        if topic == ELLIPSOIDS_TOPIC:
            for e in SceneUpdate.FromString(data).entities:
                if e.spheres:
                    s = e.spheres[0]
                    self.ellipsoids[e.frame_id] = ((s.size.x / 2, s.size.y / 2, s.size.z / 2),
                                                   _q(s.pose.orientation))
                    self.draw_body(e.frame_id)
        elif topic == TF_STATIC_TOPIC:
            frames = {}
            for tf in FrameTransforms.FromString(data).transforms:
                t = tf.translation
                frames[tf.child_frame_id] = (
                    "" if tf.parent_frame_id == WORLD else tf.parent_frame_id,
                    dq.from_pose(_q(tf.rotation), (t.x, t.y, t.z)))
            for name, T in self.scene.set_fixed(frames).items():
                if self.scene.reveal(("fixed", name), dq.to_pose(T)[1], kind="frames"):
                    say(event="drawn", frame=name)
        elif topic == TF_TOPIC:
            for tf in FrameTransforms.FromString(data).transforms:
                t = tf.translation
                self.poses[tf.child_frame_id] = ((t.x, t.y, t.z), _q(tf.rotation))
                self.draw_body(tf.child_frame_id)
        else:
            name = topic[len(PLANS):]
            points = [(p.position.x, p.position.y, p.position.z)
                      for p in PosesInFrame.FromString(data).poses]
            self.scene.draw_plan(name, points)
            if points:
                end = (points[-1] if name == WORLD_PLAN
                       else self.scene.in_world(name, points[-1])[0])
                self.scene.reveal(("plan", name), end, kind="lines")
