"""Health, reflection and grpcurl against a real server."""
from __future__ import annotations

import json
import os
import shutil
import subprocess

import grpc
import pytest
from grpc_health.v1 import health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha.proto_reflection_descriptor_database import (
    ProtoReflectionDescriptorDatabase,
)

# --------------------------------------------------------------------------- health, reflection

def test_health_is_serving(server):
    with grpc.insecure_channel(server.target) as ch:
        h = health_pb2_grpc.HealthStub(ch)
        for name in ("", "dqpose.v1.Blending"):
            r = h.Check(health_pb2.HealthCheckRequest(service=name), timeout=5)
            assert r.status == health_pb2.HealthCheckResponse.SERVING


def test_reflection_lists_and_describes_the_services(server):
    with grpc.insecure_channel(server.target) as ch:
        db = ProtoReflectionDescriptorDatabase(ch)
        services = set(db.get_services())
        assert {"dqpose.v1.Blending", "grpc.health.v1.Health"} <= services
        fd = db.FindFileContainingSymbol("dqpose.v1.Blending")
        assert fd.package == "dqpose.v1"
        assert [m.name for m in fd.service[0].method] == ["Blend", "Interpolate", "BlendStream",
                                                          "BlendBatch"]
        # method symbols resolve too (ghz looks them up; the Python pool alone cannot)
        assert db.FindFileContainingSymbol("dqpose.v1.Blending.Blend").name == fd.name


def _grpcurl() -> str | None:
    """grpcurl from PATH or Go's bin dir, installed with `go install` when Go is present."""
    found = shutil.which("grpcurl")
    if found:
        return found
    go = shutil.which("go")
    if not go:
        return None
    gobin = subprocess.run([go, "env", "GOPATH"], capture_output=True, text=True).stdout.strip()
    exe = os.path.join(gobin, "bin", "grpcurl")
    if not os.path.exists(exe):
        try:
            subprocess.run([go, "install", "github.com/fullstorydev/grpcurl/cmd/grpcurl@v1.9.4"],
                           capture_output=True, timeout=600, check=True)
        except (subprocess.SubprocessError, OSError):
            return None
    return exe if os.path.exists(exe) else None


def test_grpcurl_lists_services_and_calls_blend_with_json(server):
    exe = _grpcurl()
    if exe is None:
        pytest.skip("grpcurl not installed and `go install github.com/fullstorydev/grpcurl/"
                    "cmd/grpcurl@v1.9.4` failed or Go is missing")
    out = subprocess.run([exe, "-plaintext", server.target, "list"], capture_output=True,
                         text=True, timeout=60, check=True).stdout.split()
    assert "dqpose.v1.Blending" in out and "grpc.health.v1.Health" in out
    body = {"poses": [{"position": {"x": 0.1}, "orientation": {"w": 1}},
                      {"position": {"x": 0.3}, "orientation": {"w": 1}}],
            "weights": [1, 1], "method": "METHOD_DLB"}
    res = subprocess.run([exe, "-plaintext", "-d", json.dumps(body), server.target,
                          "dqpose.v1.Blending/Blend"], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr
    assert json.loads(res.stdout)["pose"]["position"]["x"] == pytest.approx(0.2)
    body["poses"][1]["orientation"] = {}
    res = subprocess.run([exe, "-plaintext", "-d", json.dumps(body), server.target,
                          "dqpose.v1.Blending/Blend"], capture_output=True, text=True, timeout=60)
    assert "InvalidArgument" in res.stderr and "poses[1].orientation: zero quaternion" in res.stderr
