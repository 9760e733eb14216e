"""What a recording and its live view are set up with, below the recorder and its writer (which
import them from here, the package re-exporting them): the bounds, the live view's address and
token rules, the health service's name, and the check that a directory can be written."""
from __future__ import annotations

import errno
import os

#: a recorded plan's poses at most (its samples thinned evenly, the last kept)
PLAN_VIEW_POSES = 1000

#: the modules of the [record] extra
MODULES = ("foxglove", "mcap", "foxglove_schemas_protobuf")

#: the environment variable that hands the writer process the live view's token
LIVE_TOKEN_ENV = "DQPOSE_LIVE_TOKEN"

#: where ``--live`` without a value listens (Foxglove's default for a WebSocket connection)
DEFAULT_HOST, DEFAULT_PORT = "127.0.0.1", 8765


def parse_address(text: str | None) -> tuple[str, int]:
    """``HOST:PORT``, ``:PORT`` or ``HOST`` (``None``: the default) as ``(host, port)``;
    ``ValueError`` naming ``--live`` for anything else."""
    if not text:
        return DEFAULT_HOST, DEFAULT_PORT
    host, sep, port = text.rpartition(":")
    if not sep:
        host, port = text, str(DEFAULT_PORT)
    host = host.strip("[]") or DEFAULT_HOST
    if not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ValueError(f"--live: expected HOST:PORT with a port within 0..65535, got {text!r}")
    return host, int(port)


#: the health service (grpc.health.v1) that says whether the recording's files are written:
#: NOT_SERVING while they fail (a full disk), the server's own "" staying SERVING
HEALTH_SERVICE = "dqpose.record"

#: bytes a probe of a recording's directory writes (about a chunk: what the next write needs)
PROBE_BYTES = 16 << 10


def cannot_write(directory: str) -> OSError | None:
    """Why no file can be written into ``directory`` now (read-only, no permission, full), found
    by writing and removing a probe file of :data:`PROBE_BYTES`; ``None`` when one can."""
    import tempfile

    try:
        fd, path = tempfile.mkstemp(prefix=".dqpose-probe-", dir=directory)
    except OSError as e:
        return e
    try:
        left = memoryview(bytes(PROBE_BYTES))
        while left:
            left = left[os.write(fd, left):]
        return None
    except OSError as e:
        return e
    finally:
        os.close(fd)
        os.unlink(path)


def describe(error: BaseException) -> str:
    """An OS error as its text and symbol (``No space left on device (ENOSPC)``), another as
    its text."""
    if isinstance(error, OSError) and error.errno is not None and error.errno in errno.errorcode:
        return f"{error.strerror or error} ({errno.errorcode[error.errno]})"
    return str(error) or type(error).__name__


def loopback(host: str) -> bool:
    """Whether every address ``host`` names is a loopback one (reachable from this machine
    alone); ``False`` for a name that does not resolve."""
    import ipaddress
    import socket

    try:
        infos = socket.getaddrinfo(host.strip("[]"), None, type=socket.SOCK_STREAM)
    except OSError:
        return False
    return all(ipaddress.ip_address(str(info[4][0]).split("%")[0]).is_loopback
               for info in infos)


def live_problem(host: str, port: int, token: str | None, insecure: bool) -> str | None:
    """Why ``--live HOST:PORT`` may not start: beyond the loopback it asks for the server's
    token (``--token-file``), or is told not to (``--live-insecure``)."""
    if token is None and not insecure and not loopback(host):
        return (f"--live {host}:{port}: beyond the loopback the live view asks for the server's "
                f"token (--token-file); --live-insecure serves it to anyone who reaches it")
    return None


class LiveFailed(Exception):
    """The live server did not start (the address is taken, ...): the message says why."""
