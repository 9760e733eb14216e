"""deploy/kubernetes/ validated offline: every Kubernetes object against the schemas
kubernetes-validate bundles (strict: an unknown field is an error), the pieces that must agree
(labels, ports, probes, the replica name) checked against each other, and Envoy's route
checked for what makes worlds sticky."""
from __future__ import annotations

import os

import pytest
import yaml

from dqpose.cli.cluster import BEHIND_PROXY
from dqpose.rpc import routing

kv = pytest.importorskip("kubernetes_validate", reason="the [test] extra's kubernetes-validate")

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
KUBE = os.path.join(ROOT, "deploy", "kubernetes")
#: the oldest Kubernetes the files are for (gRPC probes are GA since 1.27) and the newest bundled
VERSIONS = ("1.27.0", kv.latest_version())


def _documents(name):
    with open(os.path.join(KUBE, name)) as f:
        return [d for d in yaml.safe_load_all(f) if d]


def _objects():
    with open(os.path.join(KUBE, "kustomization.yaml")) as f:
        kustomization = yaml.safe_load(f)
    return {(d["kind"], d["metadata"]["name"]): d
            for name in kustomization["resources"] for d in _documents(name)}


@pytest.mark.parametrize("version", VERSIONS)
def test_every_object_validates_strictly(version):
    objects = _objects()
    assert {"StatefulSet", "Service", "PodDisruptionBudget", "Deployment"} <= \
        {kind for kind, _ in objects}
    for obj in objects.values():
        kv.validate(obj, version, strict=True)      # raises ValidationError naming the field


def test_a_broken_object_is_refused():
    """The validation above can fail: a misspelt field is caught."""
    obj = _objects()[("StatefulSet", "dqpose")]
    obj["spec"]["template"]["spec"]["containers"][0]["readinessProbe"]["grpcc"] = {"port": 1}
    with pytest.raises(kv.ValidationError):
        kv.validate(obj, VERSIONS[-1], strict=True)


def test_the_pieces_agree():
    objects = _objects()
    sts = objects[("StatefulSet", "dqpose")]
    svc = objects[("Service", "dqpose")]
    pdb = objects[("PodDisruptionBudget", "dqpose")]
    labels = sts["spec"]["template"]["metadata"]["labels"]
    assert svc["spec"]["clusterIP"] == "None" and sts["spec"]["serviceName"] == "dqpose"
    for selector in (svc["spec"]["selector"], sts["spec"]["selector"]["matchLabels"],
                     pdb["spec"]["selector"]["matchLabels"]):
        assert selector.items() <= labels.items()
    container = sts["spec"]["template"]["spec"]["containers"][0]
    args = container["args"]
    port = int(args[args.index("--port") + 1])
    assert {p["containerPort"] for p in container["ports"] if p["name"] == "grpc"} == {port}
    for probe in ("readinessProbe", "livenessProbe", "startupProbe"):
        assert container[probe]["grpc"]["port"] == port
    # the replica's name is its pod's, which the StatefulSet keeps stable
    assert args[args.index("--replica-name") + 1] == "$(POD_NAME)"
    # behind Envoy every client is one peer: its bounds are the server's
    for flag, value in zip(BEHIND_PROXY[::2], BEHIND_PROXY[1::2]):
        assert args[args.index(flag) + 1] == value
    assert any(e["name"] == "POD_NAME" and e["valueFrom"]["fieldRef"]["fieldPath"]
               == "metadata.name" for e in container["env"])
    # the kubelet's SIGKILL comes after the server's drain and grace
    drain, grace = (float(args[args.index(f) + 1]) for f in ("--drain", "--grace"))
    assert sts["spec"]["template"]["spec"]["terminationGracePeriodSeconds"] > drain + grace
    assert container["resources"]["requests"]["memory"]
    assert pdb["spec"]["maxUnavailable"] == 1


def _envoy():
    with open(os.path.join(KUBE, "envoy.yaml")) as f:
        return yaml.safe_load(f)


def _types(node):
    if isinstance(node, dict):
        if "@type" in node:
            yield node["@type"]
        for v in node.values():
            yield from _types(v)
    elif isinstance(node, list):
        for v in node:
            yield from _types(v)


def test_envoy_hashes_the_world_header_onto_a_ring_of_the_replicas():
    envoy = _envoy()
    clusters = {c["name"]: c for c in envoy["static_resources"]["clusters"]}
    [listener] = envoy["static_resources"]["listeners"]
    [hcm] = listener["filter_chains"][0]["filters"]
    config = hcm["typed_config"]
    routes = [r for vh in config["route_config"]["virtual_hosts"] for r in vh["routes"]]
    assert routes
    for r in routes:
        cluster = clusters[r["route"]["cluster"]]
        assert r["route"]["hash_policy"] == [{"header": {"header_name": routing.WORLD_HEADER}}]
        assert cluster["lb_policy"] in ("RING_HASH", "MAGLEV")
        assert "grpc_health_check" in cluster["health_checks"][0]
        options = cluster["typed_extension_protocol_options"][
            "envoy.extensions.upstreams.http.v3.HttpProtocolOptions"]
        assert "http2_protocol_options" in options["explicit_http_config"]
        # the headless Service's DNS name: one host per pod
        address = cluster["load_assignment"]["endpoints"][0]["lb_endpoints"][0]["endpoint"][
            "address"]["socket_address"]
        assert address["address"].startswith("dqpose.") and cluster["type"] == "STRICT_DNS"
        assert address["port_value"] == 50051
    assert config["codec_type"] == "HTTP2"
    assert config["http_filters"][-1]["name"] == "envoy.filters.http.router"
    # every typed config is one of Envoy's v3 API messages
    types = list(_types(envoy))
    assert types and all(t.startswith("type.googleapis.com/envoy.") and ".v3." in t
                         for t in types)
