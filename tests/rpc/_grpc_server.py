"""Test helpers: a real dqpose gRPC server on 127.0.0.1 (ephemeral port) in a background thread,
and throwaway certificates."""
from __future__ import annotations

import asyncio
import datetime
import ipaddress
import threading

from dqpose.rpc.server import ServerConfig, start


class ServerThread:
    """``dqpose.rpc.server.start`` on its own event loop; ``.port``, ``.target``, ``.stop()``."""

    def __init__(self, cfg: ServerConfig | None = None, **kw):
        cfg = cfg or ServerConfig(port=0, **kw)
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self.thread.start()
        self.running = asyncio.run_coroutine_threadsafe(start(cfg), self.loop).result(30)
        self.port = self.running.port
        self.target = f"127.0.0.1:{self.port}"
        self._stop_lock = threading.Lock()    # a test may stop it from a thread and again after

    def stop(self, grace: float | None = 0) -> None:
        with self._stop_lock:
            if self.loop.is_running():
                asyncio.run_coroutine_threadsafe(self.running.stop(grace), self.loop).result(30)
                self.loop.call_soon_threadsafe(self.loop.stop)
                self.thread.join(10)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.stop()


def read_in_thread(stream, into: list, ends, on_error) -> threading.Thread:
    """A daemon thread (started) that appends each item of ``stream`` to ``into``; an exception
    of type ``ends`` that ends the stream goes to ``on_error``."""
    def run() -> None:
        try:
            for item in stream:
                into.append(item)
        except ends as e:
            on_error(e)
    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread


def make_pki() -> dict[str, bytes]:
    """A CA, a server certificate for 127.0.0.1/localhost and a client certificate (PEM), plus a
    second, unrelated CA with its own client certificate."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    now = datetime.datetime.now(datetime.timezone.utc)

    def name(cn):
        return x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, cn)])

    def cert(subject, key, issuer, issuer_key, ca=False, san=None):
        b = (x509.CertificateBuilder().subject_name(name(subject)).issuer_name(name(issuer))
             .public_key(key.public_key()).serial_number(x509.random_serial_number())
             .not_valid_before(now - datetime.timedelta(minutes=5))
             .not_valid_after(now + datetime.timedelta(days=1))
             .add_extension(x509.BasicConstraints(ca=ca, path_length=None), critical=True))
        if san:
            b = b.add_extension(x509.SubjectAlternativeName(san), critical=False)
        return b.sign(issuer_key, hashes.SHA256())

    def pem_key(k):
        return k.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                               serialization.NoEncryption())

    def pem(c):
        return c.public_bytes(serialization.Encoding.PEM)

    out = {}
    for prefix in ("", "other_"):
        ca_key = ec.generate_private_key(ec.SECP256R1())
        ca = cert(prefix + "dqpose test CA", ca_key, prefix + "dqpose test CA", ca_key, ca=True)
        cl_key = ec.generate_private_key(ec.SECP256R1())
        out[prefix + "ca"] = pem(ca)
        out[prefix + "client_cert"] = pem(cert(prefix + "client", cl_key,
                                               prefix + "dqpose test CA", ca_key))
        out[prefix + "client_key"] = pem_key(cl_key)
        if not prefix:
            sv_key = ec.generate_private_key(ec.SECP256R1())
            out["server_cert"] = pem(cert("localhost", sv_key, "dqpose test CA", ca_key, san=[
                x509.DNSName("localhost"), x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]))
            out["server_key"] = pem_key(sv_key)
    return out
