"""The metrics port (issue 36, P5): it binds the loopback unless told otherwise, whatever the
server's own address, and with the server's bearer token a scrape must send it."""
from __future__ import annotations

import urllib.error
import urllib.request

import pytest

from dqpose.rpc.server import ServerConfig
from tests.rpc._grpc_server import ServerThread
from tests.rpc.server._blending import socket_free_port


def scrape(port: int, authorization: str | None = None) -> tuple[int, str]:
    request = urllib.request.Request(f"http://127.0.0.1:{port}/metrics")
    if authorization is not None:
        request.add_header("Authorization", authorization)
    try:
        with urllib.request.urlopen(request, timeout=10) as r:
            return r.status, r.read().decode()
    except urllib.error.HTTPError as e:
        return e.code, e.read().decode()


def test_metrics_bind_the_loopback_even_when_the_server_listens_beyond_it():
    with socket_free_port() as port, \
            ServerThread(ServerConfig(host="0.0.0.0", port=0, metrics_port=port)) as s:
        assert s.running.metrics.server.server_address == ("127.0.0.1", port)
        assert scrape(port)[0] == 200
    with socket_free_port() as port, \
            ServerThread(ServerConfig(port=0, metrics_port=port, metrics_host="0.0.0.0")) as s:
        assert s.running.metrics.server.server_address == ("0.0.0.0", port)


@pytest.mark.parametrize("authorization", [None, "Bearer", "Bearer wrong", "Bearer t0ken0",
                                           "t0ken", "Basic dDBrZW4="])
def test_with_a_token_a_scrape_without_it_is_refused(authorization):
    with socket_free_port() as port, \
            ServerThread(ServerConfig(port=0, metrics_port=port, token="t0ken")) as s:
        status, body = scrape(port, authorization)
        assert (status, body) == (401, "authorization: missing or invalid bearer token (send "
                                       "'Authorization: Bearer <token>', the server's "
                                       "--token-file)\n")
        status, body = scrape(port, "Bearer t0ken")
        assert status == 200 and "dqpose_grpc_calls" in body
        assert s.running.metrics.server.server_address[0] == "127.0.0.1"
