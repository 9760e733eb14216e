"""What the page serves, to whom. viser serves the page's files over HTTP and the scene over a
WebSocket on the same port (``--host``, the loopback unless told otherwise). Two ways around
that bind are closed here:

- a web page of another origin open in the user's browser can open a WebSocket to
  ``ws://127.0.0.1:PORT`` (browsers do not apply the same-origin policy to WebSockets) and read
  every pose the page shows, or move its controls; so a WebSocket whose ``Origin`` is not the
  page's own is closed (1008) before anything is sent on it. The page's own origins: its port
  on a loopback name, on ``--host``, and, with a wildcard ``--host``, on an IP address or this
  machine's own name (a DNS-rebinding page has neither). A client without an ``Origin`` is not
  a browser and is let in (it is on the machine, or ``--host`` let it in);
- viser's "share" asks viser's server (share.viser.studio) for a public tunnel to the page, on a
  message any connected client can send: the page never asks, the message is refused (said on
  standard error; the page hides the button).

The files themselves (viser's client) hold no data; viser refuses paths out of its folder."""
from __future__ import annotations

import ipaddress
import socket
from urllib.parse import urlsplit

from dqpose.events import say_err as say

LOOPBACK = ("127.0.0.1", "localhost", "::1")
WILDCARD = ("0.0.0.0", "::", "")
#: the close code of a refused WebSocket (RFC 6455: policy violation)
REFUSED = 1008


def _is_ip(name: str) -> bool:
    try:
        ipaddress.ip_address(name)
    except ValueError:
        return False
    return True


def allowed(origin: str | None, host: str, port: int) -> bool:
    """Whether a WebSocket with ``Origin: origin`` may read the page served on ``host:port``
    (module docstring)."""
    if origin is None:
        return True
    try:
        url = urlsplit(origin)
        origin_port = url.port or {"http": 80, "https": 443}.get(url.scheme)
    except ValueError:          # a malformed port
        return False
    name = (url.hostname or "").lower()
    if url.scheme not in ("http", "https") or origin_port != port or not name:
        return False
    if name in LOOPBACK or name == host.lower():
        return True
    return host in WILDCARD and (_is_ip(name) or name in (socket.gethostname().lower(),
                                                          socket.getfqdn().lower()))


def protect(server, host: str) -> None:
    """``server`` (a ``viser.ViserServer``) serving on ``host``: WebSockets of other origins
    closed, the share tunnel refused (module docstring). viser has no public hook that sees the
    handshake's headers; without the one used here the page does not start."""
    try:
        websock = server._websock_server
        connections = websock._live_connections
        hook = websock.on_client_connect
    except AttributeError as e:
        raise RuntimeError(f"this viser ({e}) gives no access to a WebSocket's Origin: the page "
                           f"would serve any web page; install viser 1.x") from None
    port = server.get_port()

    async def check(client) -> None:
        # viser runs this before it sends the client anything
        connection = connections.get(client.client_id)
        request = getattr(connection, "request", None)
        origin = None if request is None else request.headers.get("Origin")
        if connection is not None and not allowed(origin, host, port):
            say(event="refused", origin=origin, why="a web page of another origin")
            await connection.close(REFUSED, "origin not allowed")

    hook(check)

    def no_share(*_, **__) -> None:
        say(event="refused", why="a share URL (a public tunnel to the page)")

    server.request_share_url = no_share
