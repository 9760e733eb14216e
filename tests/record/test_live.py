"""``dqpose serve --live``: a real server process, an independent WebSocket client (the
``websockets`` package) speaking Foxglove's protocol (``foxglove.sdk.v1``): the channels are
advertised with their schemas as the calls log them, and a subscriber receives the fused pose a
StreamFuse call answers, decoded with the advertised schema alone."""
from __future__ import annotations

import base64
import json
import queue
import struct
import subprocess
import sys

import grpc
import pytest

from dqpose.record.schemas import message_class
from dqpose.rpc._proto.dqpose.v1 import fusion_pb2 as pb
from dqpose.rpc.fusion import STREAM_FUSE
from tests.cli._cli import ROOT, serving
from tests.record import _stream

websockets_sync = pytest.importorskip("websockets.sync.client", reason="the [test] extra's "
                                      "websockets (pip install -e '.[test]')")
pytest.importorskip("foxglove", reason="the [record] extra")

SUBPROTOCOL = "foxglove.sdk.v1"
#: a server-to-client binary message: a message on a subscription
MESSAGE_DATA = 0x01


def event(events, name):
    return next(e for e in events if e.get("event") == name)


class Viewer:
    """A WebSocket client of the live server: advertised channels by topic, messages by
    subscription."""

    def __init__(self, ws):
        self.ws = ws
        self.channels: dict[str, list[dict]] = {}
        self.server_info: dict = {}

    def receive(self, timeout: float = 30.0):
        """The next message: a JSON operation (advertisements kept) or a binary one."""
        m = self.ws.recv(timeout=timeout)
        if isinstance(m, str):
            op = json.loads(m)
            if op["op"] == "serverInfo":
                self.server_info = op
            elif op["op"] == "advertise":
                for ch in op["channels"]:
                    self.channels.setdefault(ch["topic"], []).append(ch)
            return op
        return m

    def wait_for_topic(self, topic: str) -> dict:
        while topic not in self.channels:
            self.receive()
        return self.channels[topic][0]

    def subscribe(self, subscription: int, channel: dict) -> None:
        self.ws.send(json.dumps({"op": "subscribe", "subscriptions": [
            {"id": subscription, "channelId": channel["id"]}]}))

    def next_message(self, subscription: int) -> tuple[int, bytes]:
        """``(log time ns, payload)`` of the next message on ``subscription``."""
        while True:
            m = self.receive()
            if isinstance(m, bytes) and m[0] == MESSAGE_DATA:
                sub, ns = struct.unpack_from("<IQ", m, 1)
                if sub == subscription:
                    return ns, m[13:]


TOKEN = "s3cret-token"


@pytest.fixture()
def token_file(tmp_path):
    path = tmp_path / "token"
    path.write_text(TOKEN + "\n")
    return path


@pytest.mark.parametrize("token", [False, True], ids=["no token", "token"])
def test_a_viewer_sees_the_channels_and_receives_the_fused_pose(tmp_path, token, token_file):
    data = _stream.requests(40)
    expected = _stream.answers(data)     # the answers each request brings (in process)
    first = next(i for i, a in enumerate(expected) if a)
    body = expected[first][0].body
    # the first request after ``first`` that brings an answer for the body
    later = next(i for i in range(first + 1, len(data))
                 if any(a.body == body for a in expected[i]))
    # with a token: the client gives it in the URL and sends no Origin (not a browser)
    proc, events = serving("--live", "127.0.0.1:0", "--record", str(tmp_path / "runs"),
                           *(("--token-file", str(token_file)) if token else ()))
    requests: queue.Queue = queue.Queue()
    try:
        live = event(events, "live")
        target = event(events, "serving")["address"]
        with websockets_sync.connect(f"ws://127.0.0.1:{live['port']}"
                                     f"{f'/?token={TOKEN}' if token else ''}",
                                     subprotocols=[SUBPROTOCOL], open_timeout=30) as ws, \
                grpc.insecure_channel(target) as ch:
            viewer = Viewer(ws)
            assert ws.subprotocol == SUBPROTOCOL
            assert viewer.receive()["op"] == "serverInfo"
            call = ch.stream_stream(f"/{STREAM_FUSE}")(
                iter(requests.get, None), timeout=60,
                metadata=[("authorization", f"Bearer {TOKEN}")] if token else None)

            def send(upto: int) -> list[pb.FusedPose]:
                """Requests up to index ``upto`` sent, their answers received."""
                n = 0
                while data:
                    i = len(expected) - len(data)
                    if i > upto:
                        break
                    requests.put(data.pop(0))
                    n += len(expected[i])
                return [pb.FusedPose.FromString(next(call)) for _ in range(n)]

            send(first)
            channel = viewer.wait_for_topic(f"/fused/{body}")
            assert (channel["schemaName"], channel["encoding"]) == \
                ("foxglove.PoseInFrame", "protobuf")
            for topic, schema in (("/tf", "foxglove.FrameTransforms"),
                                  ("/fused/ellipsoids", "foxglove.SceneUpdate"),
                                  (f"/dqpose/{STREAM_FUSE}/requests",
                                   "dqpose.v1.FuseStreamRequest"),
                                  (f"/dqpose/{STREAM_FUSE}/answers", "dqpose.v1.FusedPose")):
                assert viewer.wait_for_topic(topic)["schemaName"] == schema
            viewer.subscribe(7, channel)
            # a message round trip: the subscription has reached the server before more answers
            ws.ping().wait(30)
            sent = [a for a in send(later) if a.body == body]
            assert sent
            ns, payload = viewer.next_message(7)
            cls = message_class(base64.b64decode(channel["schema"]), channel["schemaName"])
            pose = cls.FromString(payload)      # type: ignore[attr-defined]
            assert pose.frame_id == "world"
            p, q = pose.pose.position, pose.pose.orientation
            a = sent[0].pose
            assert (p.x, p.y, p.z, q.w, q.x, q.y, q.z) == (
                a.position.x, a.position.y, a.position.z, a.orientation.w, a.orientation.x,
                a.orientation.y, a.orientation.z)
            requests.put(None)
            list(call)
    finally:
        requests.put(None)
        proc.terminate()
        proc.wait(30)


def test_live_on_a_taken_port_is_one_line_and_exit_2():
    proc, events = serving("--live", "127.0.0.1:0")
    try:
        port = event(events, "live")["port"]
        res = subprocess.run([sys.executable, "-m", "dqpose.cli", "serve", "--port", "0",
                              "--live", f"127.0.0.1:{port}"], capture_output=True, text=True,
                             timeout=60, cwd=ROOT)
        assert res.returncode == 2
        last = res.stderr.strip().splitlines()[-1]
        assert last.startswith(f"dqpose serve: error: --live 127.0.0.1:{port}: "), res.stderr
        assert "in use" in last
    finally:
        proc.terminate()
        proc.wait(30)


@pytest.mark.parametrize("value", ["127.0.0.1:x", "host:70000"])
def test_a_malformed_live_address_is_named(value):
    res = subprocess.run([sys.executable, "-m", "dqpose.cli", "serve", "--live", value],
                         capture_output=True, text=True, timeout=30, cwd=ROOT)
    assert (res.returncode, res.stderr) == (
        2, f"dqpose serve: error: --live: expected HOST:PORT with a port within 0..65535, "
           f"got {value!r}\n")


def refused(url: str, origin: str | None = None, subprotocol: str = SUBPROTOCOL):
    """The HTTP status and body a WebSocket handshake to ``url`` is refused with (``None``: it
    was let in and the server said who it is)."""
    from websockets.exceptions import InvalidStatus

    try:
        with websockets_sync.connect(url, subprotocols=[subprotocol], open_timeout=30,
                                     origin=origin) as ws:
            assert json.loads(ws.recv(timeout=30))["op"] == "serverInfo"
            return None
    except InvalidStatus as e:
        return e.response.status_code, e.response.body.decode()


def test_with_a_token_a_client_without_it_or_from_another_origin_is_refused(token_file):
    proc, events = serving("--live", "127.0.0.1:0", "--token-file", str(token_file),
                           "--live-origin", "https://app.foxglove.dev")
    try:
        url = f"ws://127.0.0.1:{event(events, 'live')['port']}"
        # the client: no credential, a browser page's origin
        assert refused(url, "http://evil.example")[0] == 403
        assert refused(url, "http://evil.example")[1] == (
            "origin http://evil.example is not allowed (dqpose serve --live-origin "
            "http://evil.example)\n")
        for bad in (url, f"{url}/?token=", f"{url}/?token=s3cret", f"{url}/?token={TOKEN}x",
                    f"{url}/?tok={TOKEN}"):
            status, body = refused(bad)
            assert status == 401 and body.startswith("missing or invalid token"), bad
        assert refused(f"{url}/?token={TOKEN}", "http://evil.example")[0] == 403
        assert refused(f"{url}/?token={TOKEN}", subprotocol="foxglove.websocket.v1") == (
            400, f"the WebSocket subprotocol {SUBPROTOCOL} is expected\n")
        # let in: the token without an Origin, and with an allowed one
        assert refused(f"{url}/?token={TOKEN}") is None
        with websockets_sync.connect(f"{url}/?token={TOKEN}", subprotocols=[SUBPROTOCOL],
                                     open_timeout=30) as ws:
            # what it does not take is answered with a status, and the connection goes on
            for bad in (b"\x01abc", "{", json.dumps({"op": "setParameters"}),
                        json.dumps({"op": "subscribe", "subscriptions": [{"id": -1,
                                                                          "channelId": 1}]})):
                ws.send(bad)
            statuses = [json.loads(ws.recv(timeout=30)) for _ in range(6)][2:]
            assert [(s["op"], s["level"]) for s in statuses] == [("status", 2)] * 4
            assert "'setParameters'" in statuses[2]["message"]
            ws.ping().wait(30)
        assert refused(f"{url}/?token={TOKEN}", "https://app.foxglove.dev") is None
        assert refused(url, "https://app.foxglove.dev")[0] == 401
    finally:
        proc.terminate()
        proc.wait(30)
    lines = [json.loads(line) for line in proc.stderr.read().splitlines()
             if line.startswith('{"event": "live_refused"')]
    assert lines and lines[0]["status"] == 403 and lines[0]["peer"].startswith("127.0.0.1:")


def test_live_insecure_lets_every_client_in(token_file):
    proc, events = serving("--live", "127.0.0.1:0", "--token-file", str(token_file),
                           "--live-insecure")
    try:
        assert event(events, "live")["insecure"] is True
        assert refused(f"ws://127.0.0.1:{event(events, 'live')['port']}",
                       "http://evil.example") is None
    finally:
        proc.terminate()
        proc.wait(30)


def test_live_beyond_the_loopback_needs_a_token_or_insecure(token_file):
    res = subprocess.run([sys.executable, "-m", "dqpose.cli", "serve", "--port", "0",
                          "--live", "0.0.0.0:0"], capture_output=True, text=True, timeout=60,
                         cwd=ROOT)
    assert (res.returncode, res.stderr) == (
        2, "dqpose serve: error: --live 0.0.0.0:0: beyond the loopback the live view asks for "
           "the server's token (--token-file); --live-insecure serves it to anyone who reaches "
           "it\n")
    for flags in (("--token-file", str(token_file)), ("--live-insecure",)):
        proc, events = serving("--live", "0.0.0.0:0", *flags)
        proc.terminate()
        proc.wait(30)
        assert event(events, "live")["host"] == "0.0.0.0"


def test_a_latched_channels_last_message_reaches_a_later_subscriber():
    """``/tf_static`` (logged once a Configure, usually before a viewer connects): a client
    that subscribes later gets its last message first, then what follows; ``/tf``'s messages
    before the subscription are not kept. In process, the live server alone."""
    from dqpose.record import views
    from dqpose.record.live import LiveServer
    from dqpose.record.topics import TF_STATIC_TOPIC, TF_TOPIC
    from tests._polling import wait_until

    def table(x: float) -> bytes:
        return views.frame_transforms(0, [("world", "table", (x, 0.0, 0.0),
                                           (1.0, 0.0, 0.0, 0.0))]).SerializeToString()

    live = LiveServer("127.0.0.1", 0, insecure=True)
    try:
        static = live.channel(TF_STATIC_TOPIC, views.FrameTransforms)
        tf = live.channel(TF_TOPIC, views.FrameTransforms)
        for ns, x in ((5, 1.0), (6, 2.0)):
            live.write(static, ns, table(x))
            live.write(tf, ns, table(x))
        with websockets_sync.connect(f"ws://127.0.0.1:{live.port}", subprotocols=[SUBPROTOCOL],
                                     open_timeout=30) as ws:
            viewer = Viewer(ws)
            viewer.subscribe(1, viewer.wait_for_topic(TF_STATIC_TOPIC))
            viewer.subscribe(2, viewer.wait_for_topic(TF_TOPIC))
            assert viewer.next_message(1) == (6, table(2.0))
            assert wait_until(lambda: tf.subscribers, 30)   # taken by the server (in process)
            live.write(tf, 7, table(3.0))
            live.write(static, 8, table(4.0))
            assert viewer.next_message(2) == (7, table(3.0))
            assert viewer.next_message(1) == (8, table(4.0))
    finally:
        live.close()
