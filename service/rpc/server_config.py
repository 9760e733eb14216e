"""What a dqpose server starts with (:class:`ServerConfig`) and the checks of every value, TLS
files included, for ``dqpose serve`` and Python callers alike."""
from __future__ import annotations

import contextlib
import dataclasses
import math
import numbers
import os
import socket
import ssl
import tempfile

from dqpose import limits as limits_table
from dqpose.rpc import DEFAULT_MAX_MESSAGE_BYTES, DEFAULT_MAX_POSES, routing


class ConfigError(ValueError):
    """A :class:`ServerConfig` value the server cannot start with: ``setting`` names the field,
    ``problem`` says what is wrong (with the allowed range); ``str()`` is ``"setting: problem"``."""

    def __init__(self, setting: str, problem: str):
        super().__init__(f"{setting}: {problem}")
        self.setting, self.problem = setting, problem


INT32_MAX = 2**31 - 1   # gRPC's channel arguments (sizes, milliseconds) are C ints


@dataclasses.dataclass
class ServerConfig:
    """What a server starts with; every value is checked here (:meth:`check`, at construction
    and again by :func:`start`), for ``dqpose serve`` and Python callers alike."""

    host: str = "127.0.0.1"
    port: int = 50051                  # 0 picks a free port
    tls_cert: bytes | None = None      # PEM chain; with tls_key enables TLS
    tls_key: bytes | None = None
    client_ca: bytes | None = None     # PEM; requires and verifies client certificates (mTLS)
    token: str | None = None           # bearer token required on every RPC except health
    max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES
    max_poses: int = DEFAULT_MAX_POSES  # per request: poses, keyframes and sampled times
    keepalive_s: float = 60.0
    grace_s: float = 10.0              # time calls in flight get to finish once the listener closes
    drain_s: float = 0.5               # on SIGTERM (serve): health NOT_SERVING, new calls
                                       # UNAVAILABLE, the listener still open
    metrics_port: int | None = None
    # where the metrics port listens: the loopback unless told (it asks for the token when
    # there is one)
    metrics_host: str = "127.0.0.1"
    # Arms that Trajectories.Execute may drive, by the name a request gives (opened by whoever
    # starts the server: `dqpose serve --arm NAME=SPEC`), and ``executor(arm, trajectory)``,
    # which starts running a plan on one (drivers.executor; this package imports no driver).
    arms: dict = dataclasses.field(default_factory=dict)
    executor: object = None
    # a dqpose.record Recorder every servicer records its calls to (`dqpose serve --record`),
    # made by whoever starts the server, which closes it when it stops; None records nothing
    recorder: object = None
    # what one request or stream may cost (service/limits.py: the table, its cost model and
    # the `dqpose serve` flag of each)
    limits: limits_table.Limits = limits_table.DEFAULT
    # the name every answer carries in x-dqpose-replica (dqpose.rpc.routing), for a client behind
    # a load balancer to see which replica holds its world
    replica_name: str = dataclasses.field(default_factory=socket.gethostname)

    def __post_init__(self):
        self.check()

    def check(self) -> None:
        """Raises :class:`ConfigError` for the first value out of range, and for a certificate,
        key or client CA that does not load (checked here because gRPC, given one, only says
        that it failed to bind)."""
        _integer(self, "port", 0, 65535)
        if self.metrics_port is not None:
            _integer(self, "metrics_port", 1, 65535)
        if not (isinstance(self.metrics_host, str) and self.metrics_host):
            raise ConfigError("metrics_host", f"must be a host name or address, got "
                                              f"{self.metrics_host!r}")
        _integer(self, "max_message_bytes", 1, INT32_MAX)
        # a message of at most INT32_MAX bytes holds fewer poses than that
        _integer(self, "max_poses", 1, INT32_MAX)
        _seconds(self, "keepalive_s", 0.001, INT32_MAX // 1000)
        _seconds(self, "grace_s")
        _seconds(self, "drain_s")
        _check_tls(self.tls_cert, self.tls_key, self.client_ca)
        try:
            routing.check_name("replica_name", self.replica_name, routing.MAX_REPLICA_NAME)
        except ValueError as e:
            raise ConfigError("replica_name", str(e).split(": ", 1)[1]) from None
        if not self.replica_name:
            raise ConfigError("replica_name", "must not be empty")
        for name in self.arms:
            if not (isinstance(name, str) and name.isidentifier()):
                raise ConfigError("arms", f"an arm's name must be a word (letters, digits, _), "
                                          f"got {name!r}")
        if self.arms and not callable(self.executor):
            raise ConfigError("executor", "arms need an executor to run plans on them")
        if not isinstance(self.limits, limits_table.Limits):
            raise ConfigError("limits", f"must be a dqpose.limits.Limits, got "
                                        f"{type(self.limits).__name__}")
        try:
            self.limits.check()
        except limits_table.LimitConfigError as e:
            raise ConfigError(e.setting, e.problem) from None


def _integer(cfg, name: str, lo: int, hi: int) -> None:
    v = getattr(cfg, name)
    if isinstance(v, bool) or not isinstance(v, numbers.Integral):
        raise ConfigError(name, f"must be an integer, got {v!r}")
    if not lo <= int(v) <= hi:      # int(): the numbers ABCs declare no comparisons
        raise ConfigError(name, f"must be within {lo}..{hi}, got {v}")


def _seconds(cfg, name: str, lo: float = 0.0, hi: float | None = None) -> None:
    v = getattr(cfg, name)
    if isinstance(v, bool) or not isinstance(v, numbers.Real):
        raise ConfigError(name, f"must be a number of seconds, got {v!r}")
    if hi is None:
        if not (math.isfinite(v) and float(v) >= lo):
            raise ConfigError(name, f"must be a finite number of seconds >= {lo:g}, got {v:g}")
    elif not lo <= float(v) <= hi:
        raise ConfigError(name, f"must be within {lo:g}..{hi} seconds, got {v:g}")


# --------------------------------------------------------------------------- TLS files

@contextlib.contextmanager
def _pem_path(data: bytes):
    """A path that holds ``data``, for OpenSSL, which loads keys and chains only from files: an
    anonymous in-memory file where the OS has them (the key never touches a disk), else a
    private temporary directory."""
    try:
        fd = os.memfd_create("dqpose-pem")
    except (AttributeError, OSError):
        with tempfile.TemporaryDirectory() as d:     # mode 0700
            path = os.path.join(d, "pem")
            with open(path, "wb") as f:
                f.write(data)
            yield path
        return
    try:
        os.write(fd, data)
        yield f"/proc/self/fd/{fd}"
    finally:
        os.close(fd)


def _certificates(setting: str, data: bytes) -> None:
    """Every PEM certificate in ``data`` parses, and there is one."""
    try:
        ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT).load_verify_locations(cadata=data.decode("ascii"))
    except (UnicodeDecodeError, ssl.SSLError):
        raise ConfigError(setting, "no PEM certificate in it") from None


class _Encrypted(Exception):
    pass


def _encrypted():
    raise _Encrypted   # rather than OpenSSL's prompt on the terminal


def _check_tls(cert: bytes | None, key: bytes | None, client_ca: bytes | None) -> None:
    """The certificate chain, its key and the client CA load, as gRPC will load them, and the
    key is the certificate's (OpenSSL here, BoringSSL in gRPC: the same PEM formats)."""
    if not (cert or key):
        if client_ca:
            raise ConfigError("client_ca", "mTLS needs a server certificate and key (TLS)")
        return
    if not cert:
        raise ConfigError("tls_cert", "TLS needs a certificate with the key")
    if not key:
        raise ConfigError("tls_key", "TLS needs a private key with the certificate")
    _certificates("tls_cert", cert)
    with _pem_path(cert) as cert_path, _pem_path(key) as key_path:
        try:
            ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER).load_cert_chain(cert_path, key_path,
                                                                     password=_encrypted)
        except _Encrypted:
            raise ConfigError("tls_key", "encrypted private keys are not supported") from None
        except ssl.SSLError as e:
            if "KEY_VALUES_MISMATCH" in str(e):
                raise ConfigError("tls_key", "the private key does not match the "
                                             "certificate") from None
            raise ConfigError("tls_key", "no PEM private key in it") from None
    if client_ca:
        _certificates("client_ca", client_ca)
