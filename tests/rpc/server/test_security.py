"""Bearer tokens, TLS and mTLS; start options and certificates checked before binding."""
from __future__ import annotations

import math
import subprocess
import sys

import grpc
import pytest
from grpc_health.v1 import health_pb2, health_pb2_grpc

from dqpose.rpc._proto.dqpose.v1 import blending_pb2_grpc as pb_grpc
from dqpose.rpc.server import ServerConfig, start
from tests.rpc._grpc_server import ServerThread, make_pki
from tests.rpc.server._blending import (
    ROOT,
    _blend_ok,
    _code,
    _poses,
    blend_req,
)

# --------------------------------------------------------------------------- security





def test_bearer_token_accepted_and_rejected():
    with ServerThread(token="s3cret-token") as s, grpc.insecure_channel(s.target) as ch:
        assert _blend_ok(ch, [("authorization", "Bearer s3cret-token")]).pose.orientation.w == 1.0
        code, details = _code(lambda: _blend_ok(ch))
        assert code == grpc.StatusCode.UNAUTHENTICATED and "missing bearer token" in details
        code, details = _code(lambda: _blend_ok(ch, [("authorization", "Bearer s3cret-tokeX")]))
        assert code == grpc.StatusCode.UNAUTHENTICATED
        assert details == "authorization: invalid bearer token"
        stream = pb_grpc.BlendingStub(ch).BlendStream(iter([blend_req(*_poses(2))]), timeout=5)
        assert _code(lambda: list(stream))[0] == grpc.StatusCode.UNAUTHENTICATED
        # health stays open for load balancers and HEALTHCHECK
        r = health_pb2_grpc.HealthStub(ch).Check(health_pb2.HealthCheckRequest(), timeout=5)
        assert r.status == health_pb2.HealthCheckResponse.SERVING


@pytest.fixture(scope="module")
def pki():
    return make_pki()


def test_tls_accepted_with_the_ca_and_rejected_without(pki):
    with ServerThread(tls_cert=pki["server_cert"], tls_key=pki["server_key"]) as s:
        creds = grpc.ssl_channel_credentials(pki["ca"])
        with grpc.secure_channel(s.target, creds) as ch:
            assert _blend_ok(ch).pose.orientation.w == 1.0
        with grpc.secure_channel(s.target, grpc.ssl_channel_credentials(pki["other_ca"])) as ch:
            assert _code(lambda: _blend_ok(ch))[0] == grpc.StatusCode.UNAVAILABLE
        with grpc.insecure_channel(s.target) as ch:  # plaintext against TLS
            assert _code(lambda: _blend_ok(ch))[0] == grpc.StatusCode.UNAVAILABLE


def test_mtls_needs_a_client_certificate_from_the_client_ca(pki):
    with ServerThread(tls_cert=pki["server_cert"], tls_key=pki["server_key"],
                      client_ca=pki["ca"]) as s:
        good = grpc.ssl_channel_credentials(pki["ca"], pki["client_key"], pki["client_cert"])
        with grpc.secure_channel(s.target, good) as ch:
            assert _blend_ok(ch).pose.orientation.w == 1.0
        for creds in (grpc.ssl_channel_credentials(pki["ca"]),
                      grpc.ssl_channel_credentials(pki["ca"], pki["other_client_key"],
                                                   pki["other_client_cert"])):
            with grpc.secure_channel(s.target, creds) as ch:
                assert _code(lambda: _blend_ok(ch))[0] == grpc.StatusCode.UNAVAILABLE


# --------------------------------------------------------------------------- start options

@pytest.mark.parametrize("field, value, message", [
    ("port", 116686, "port: must be within 0..65535, got 116686"),
    ("port", -1, "port: must be within 0..65535, got -1"),
    ("port", 5.5, "port: must be an integer, got 5.5"),
    ("metrics_port", 0, "metrics_port: must be within 1..65535, got 0"),
    ("max_message_bytes", -1, "max_message_bytes: must be within 1..2147483647, got -1"),
    ("max_message_bytes", 2**31, "max_message_bytes: must be within 1..2147483647, got 2147483648"),
    ("max_poses", 0, "max_poses: must be within 1..2147483647, got 0"),
    ("max_poses", -5, "max_poses: must be within 1..2147483647, got -5"),
    ("grace_s", -1.0, "grace_s: must be a finite number of seconds >= 0, got -1"),
    ("grace_s", math.nan, "grace_s: must be a finite number of seconds >= 0, got nan"),
    ("drain_s", -0.5, "drain_s: must be a finite number of seconds >= 0, got -0.5"),
    ("keepalive_s", 0.0, "keepalive_s: must be within 0.001..2147483 seconds, got 0"),
    ("keepalive_s", math.inf, "keepalive_s: must be within 0.001..2147483 seconds, got inf"),
])
def test_start_options_out_of_range_are_a_value_error_naming_the_field(field, value, message):
    import asyncio

    with pytest.raises(ValueError) as e:
        ServerConfig(**{"port": 0, field: value})
    assert str(e.value) == message
    cfg = ServerConfig(port=0)
    setattr(cfg, field, value)          # changed after construction: start() checks again
    with pytest.raises(ValueError) as e:
        asyncio.run(start(cfg))
    assert str(e.value) == message


def _bad_pem(pki) -> list[tuple[dict, str]]:
    """(ServerConfig PEM fields, the message) for a bad certificate, a bad or mismatched key
    and a garbage client CA."""
    from cryptography.hazmat.primitives import serialization

    cert, key = pki["server_cert"], pki["server_key"]
    broken = cert[:100] + cert[-40:]          # PEM armour around a broken body
    encrypted = serialization.load_pem_private_key(key, None).private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
        serialization.BestAvailableEncryption(b"secret"))
    return [
        (dict(tls_cert=b"not a certificate", tls_key=key),
         "tls_cert: no PEM certificate in it"),
        (dict(tls_cert=broken, tls_key=key), "tls_cert: no PEM certificate in it"),
        (dict(tls_cert=key, tls_key=key), "tls_cert: no PEM certificate in it"),
        (dict(tls_cert=cert, tls_key=b"garbage"), "tls_key: no PEM private key in it"),
        (dict(tls_cert=cert, tls_key=pki["client_key"]),
         "tls_key: the private key does not match the certificate"),
        # gRPC cannot use it; OpenSSL would ask for the password on the terminal
        (dict(tls_cert=cert, tls_key=encrypted),
         "tls_key: encrypted private keys are not supported"),
        (dict(tls_cert=cert, tls_key=key, client_ca=b"garbage"),
         "client_ca: no PEM certificate in it"),
        (dict(tls_cert=cert, tls_key=key, client_ca="\u00e9t\u00e9".encode()),
         "client_ca: no PEM certificate in it"),
    ]


def test_bad_certificates_keys_and_client_cas_are_named_before_binding(pki):
    import asyncio

    for fields, message in _bad_pem(pki):
        with pytest.raises(ValueError) as e:
            asyncio.run(start(ServerConfig(port=0, **fields)))
        assert str(e.value) == message, fields


def test_serve_names_the_bad_pem_file_and_the_problem(pki, tmp_path):
    for i, (fields, message) in enumerate(_bad_pem(pki)):
        args = []
        for field, data in fields.items():
            path = tmp_path / f"{i}-{field}.pem"
            path.write_bytes(data)
            args += ["--" + field.replace("_", "-"), str(path)]
        setting, problem = message.split(": ", 1)
        flag = "--" + setting.replace("_", "-")
        res = subprocess.run([sys.executable, "-m", "dqpose.cli", "serve", "--port", "0", *args],
                             capture_output=True, text=True, timeout=30, cwd=ROOT)
        assert res.returncode == 2, res.stderr
        assert res.stderr == (f"dqpose serve: error: {flag} {tmp_path}/{i}-{setting}.pem: "
                              f"{problem}\n")
