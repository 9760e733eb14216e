"""docker/compose.yaml's cluster profile validated offline against the HAProxy configuration it
mounts (no Docker daemon runs here): the replicas HAProxy's backend names are the profile's
services, each serving on the port HAProxy dials, named as its service, draining for longer than
one health check; HAProxy's bind port is the one the profile publishes."""
from __future__ import annotations

import os
import re

import yaml

from dqpose.cli.cluster import BEHIND_PROXY

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
DOCKER = os.path.join(ROOT, "docker")


def _compose() -> dict:
    with open(os.path.join(DOCKER, "compose.yaml")) as f:
        return yaml.safe_load(f)


def _flag(command: list, name: str) -> str:
    return command[command.index(name) + 1]


def test_the_cluster_profile_serves_what_haproxy_dials():
    with open(os.path.join(DOCKER, "haproxy.cfg")) as f:
        cfg = f.read()
    servers = dict(re.findall(r"^\s*server (\S+) (\S+:\d+)", cfg, re.MULTILINE))
    bind = int(re.search(r"^\s*bind :(\d+) proto h2", cfg, re.MULTILINE)[1])
    check_ms = int(re.search(r"check inter (\d+)ms", cfg)[1])
    services = _compose()["services"]
    cluster = {name: s for name, s in services.items() if "cluster" in s.get("profiles", ())}
    proxy = cluster.pop("haproxy")
    assert set(cluster) == set(servers) and len(cluster) == 3
    for name, service in cluster.items():
        host, port = servers[name].rsplit(":", 1)
        command = service["command"]
        assert host == name                                    # compose's DNS name
        assert command[0] == "serve" and _flag(command, "--port") == port
        assert _flag(command, "--host") == "0.0.0.0"
        assert _flag(command, "--replica-name") == name       # x-dqpose-replica says which
        assert float(_flag(command, "--drain")) * 1000 > check_ms
        # behind the proxy every client is one peer: its bounds are the server's
        for flag, value in zip(BEHIND_PROXY[::2], BEHIND_PROXY[1::2]):
            assert _flag(command, flag) == value
    assert "./haproxy.cfg:/usr/local/etc/haproxy/haproxy.cfg:ro" in proxy["volumes"]
    assert any(p.endswith(f":{bind}") for p in proxy["ports"])
    assert set(proxy["depends_on"]) == set(cluster)
