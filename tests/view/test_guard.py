"""Who the page serves (dqpose.view.guard), against a real page: a WebSocket opened by a web page
of another origin is closed before the page sends it anything, the page's own origin and a
client without an Origin (not a browser) get the scene; a request for viser's public share
tunnel is refused; the page listens on the loopback only (what the kernel says it bound)."""
from __future__ import annotations

import threading

import pytest

from tests._polling import wait_until

pytest.importorskip("viser", reason="the [view] extra (pip install -e '.[view]')")
pytest.importorskip("websockets", reason="the [view] extra")


@pytest.mark.parametrize("origin, host, ok", [
    (None, "127.0.0.1", True),
    ("http://127.0.0.1:8080", "127.0.0.1", True),
    ("http://localhost:8080", "127.0.0.1", True),
    ("http://[::1]:8080", "127.0.0.1", True),
    ("http://evil.example", "127.0.0.1", False),
    ("http://evil.example:8080", "127.0.0.1", False),      # DNS rebinding: the page's port
    ("http://127.0.0.1:3000", "127.0.0.1", False),         # another page on the machine
    ("file://", "127.0.0.1", False),
    ("null", "127.0.0.1", False),
    ("http://127.0.0.1:notaport", "127.0.0.1", False),
    ("http://10.1.2.3:8080", "0.0.0.0", True),             # --host 0.0.0.0: by address
    ("http://evil.example:8080", "0.0.0.0", False),
    ("http://cell-pc:8080", "cell-pc", True),              # --host by name
])
def test_the_pages_own_origins(origin, host, ok):
    from dqpose.view.guard import allowed

    assert allowed(origin, host, 8080) is ok


@pytest.fixture()
def scene():
    from dqpose.view.page import Scene

    s = Scene(port=0)
    s.draw_body("box", (0.1, 0.2, 0.3), (1.0, 0, 0, 0))
    yield s
    s.close()


def _first_message(port: int, origin: str | None):
    """What the page sends first to a WebSocket opened with ``Origin: origin``: bytes, or the
    close code it ended with."""
    import viser
    from websockets.exceptions import ConnectionClosed
    from websockets.sync.client import connect

    headers = {} if origin is None else {"Origin": origin}
    with connect(f"ws://127.0.0.1:{port}", additional_headers=headers,
                            subprotocols=[f"viser-v{viser.__version__}"], open_timeout=30,
                            max_size=None) as ws:
        try:
            return ws.recv(timeout=30)
        except ConnectionClosed as e:
            return e.rcvd.code if e.rcvd else None


def test_another_origin_gets_nothing(scene):
    from dqpose.view.guard import REFUSED

    assert _first_message(scene.port, "http://evil.example") == REFUSED
    assert _first_message(scene.port, "http://evil.example:%d" % scene.port) == REFUSED
    assert isinstance(_first_message(scene.port, f"http://127.0.0.1:{scene.port}"), bytes)
    assert isinstance(_first_message(scene.port, None), bytes)


def test_a_share_tunnel_is_refused(scene, monkeypatch):
    import msgspec
    import viser
    from websockets.sync.client import connect

    from dqpose.view import guard

    said = threading.Event()
    monkeypatch.setattr(guard, "say", lambda **e: said.set())
    with connect(f"ws://127.0.0.1:{scene.port}", subprotocols=[f"viser-v{viser.__version__}"],
                 open_timeout=30) as ws:
        ws.send(msgspec.msgpack.encode({"type": "ShareUrlRequest"}))
        assert wait_until(said.is_set, timeout=30)
    assert scene.server._share_tunnel is None


def _listening() -> set[str]:
    """The local addresses (``/proc/net/tcp`` hex) this process's sockets listen on."""
    import os
    import re

    inodes = set()
    for fd in os.listdir("/proc/self/fd"):
        try:
            m = re.fullmatch(r"socket:\[(\d+)\]", os.readlink(f"/proc/self/fd/{fd}"))
        except OSError:             # listdir's own descriptor, closed since
            continue
        if m:
            inodes.add(m[1])
    found = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        with open(table) as f:
            for row in f.read().splitlines()[1:]:
                cols = row.split()
                if cols[3] == "0A" and cols[9] in inodes:              # 0A: LISTEN
                    found.add(cols[1])
    return found


def test_the_page_listens_on_the_loopback_only():
    """Every socket the page opened to listen on is bound to the loopback."""
    from dqpose.view.page import Scene

    before = _listening()
    page = Scene(port=0)
    try:
        opened = _listening() - before
    finally:
        page.close()
    assert any(a.endswith(f":{page.port:04X}") for a in opened), opened
    loopback = ("0100007F:", "00000000000000000000000001000000:")
    assert all(a.startswith(loopback) for a in opened), opened
