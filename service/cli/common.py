"""What every command shares: the exit code for errors, reading a file given on the command line,
and the options and client of the commands that call a server. Light to import: grpc is imported
when a client is made."""
from __future__ import annotations

import argparse
import contextlib
import sys

EXIT_ERROR = 2
#: a command ended by Ctrl-C (128 + SIGINT, as shells report it)
INTERRUPTED = 130


def fail(cmd: str, msg: str) -> int:
    print(f"dqpose {cmd}: error: {msg}", file=sys.stderr)
    return EXIT_ERROR


def missing_extra(cmd: str, e: Exception) -> int:
    """A module of an extra that is not installed (:class:`~dqpose.errors.MissingExtra`, or the
    ``ModuleNotFoundError`` of such a module): exit 2 saying which extra, and how to install it.
    Any other missing module is a broken install, raised on."""
    from dqpose.errors import MissingExtra, missing

    e = missing(e) if isinstance(e, ModuleNotFoundError) else e
    if not isinstance(e, MissingExtra):
        raise e
    return fail(cmd, str(e))


def read(path: str, mode: str = "rb") -> bytes:
    with open(path, mode) as f:
        return f.read()


def connection_args(p: argparse.ArgumentParser, target_alias: bool = True) -> None:
    """The options of a command that calls a server. ``--target`` (the flag's old name) stays an
    alias where no positional is named TARGET: one would read as the other."""
    g = p.add_argument_group("server connection")
    g.add_argument("--server", *(["--target"] if target_alias else []), dest="server",
                   default="127.0.0.1:50051", metavar="HOST:PORT",
                   help="the server's address (default: %(default)s)")
    g.add_argument("--token-file", help="file holding the bearer token")
    g.add_argument("--tls-ca", metavar="PEM",
                   help="CA certificate to verify the server (enables TLS)")
    g.add_argument("--tls", action="store_true", help="TLS with the system's root certificates")
    g.add_argument("--cert", metavar="PEM", help="client certificate for mTLS")
    g.add_argument("--key", metavar="PEM", help="client private key for mTLS")
    g.add_argument("--timeout", type=float, default=10.0,
                   help="deadline in seconds (default: %(default)s)")


def client(args):
    """The :class:`dqpose.rpc.client.Client` the connection options describe."""
    from dqpose.rpc.client import Client

    token = read(args.token_file, "r").strip() if args.token_file else None
    return Client(args.server, token=token, tls=args.tls,
                  root_certificates=read(args.tls_ca) if args.tls_ca else None,
                  certificate_chain=read(args.cert) if args.cert else None,
                  private_key=read(args.key) if args.key else None, timeout=args.timeout,
                  world=getattr(args, "world", "") or None)


def failure(cmd: str, args, e: Exception) -> int:
    """The one-line message and exit code of a command that computes here (``--local``) or on a
    server; what is neither bad input nor a failed call is raised on."""
    from dqpose.errors import MissingExtra

    if isinstance(e, (MissingExtra, ModuleNotFoundError)):
        return missing_extra(cmd, e)
    if not getattr(args, "local", False):
        from dqpose.rpc.client import RequestTooLarge, RpcError

        code = e.code.name if isinstance(e, RpcError) else None
        if isinstance(e, RequestTooLarge) or code == "RESOURCE_EXHAUSTED":
            return fail(cmd, f"{e}; or compute it in this process with --local")
        if code in ("UNAVAILABLE", "DEADLINE_EXCEEDED"):
            return fail(cmd, f"no answer from the server at {args.server} ({e}); start one "
                             f"with `dqpose serve`, or add --local")
        if code is not None:
            return fail(cmd, str(e))
    if isinstance(e, (OSError, ValueError)):
        return fail(cmd, str(e))
    raise e


def open_arm(spec, process: bool, simulated: bool, **kwargs):
    """``drivers.open_arm(spec, process=process, **kwargs)`` for a command that drives an arm
    and ends with it. A UR is opened with ``disconnect=False`` (its close stops the arm and ends
    the control script, and leaves ur_rtde's connections to the process's end: their disconnect
    kept a command ended by Ctrl-C alive for 2 s after its arm had stopped) wherever its
    connections close before its controller goes: in a process of its own, which the command
    ends before its simulators, or in the command's process with a controller it does not end
    (not ``simulated`` by it). On a simulator the command ends while the connections are open,
    ur_rtde's threads would print their complaints."""
    from dqpose import drivers
    s = spec if isinstance(spec, drivers.ArmSpec) else drivers.parse_arm_spec(spec)
    if s.kind == "ur" and (process or not simulated):
        kwargs.setdefault("disconnect", False)
    return drivers.open_arm(s, process=process, **kwargs)


@contextlib.contextmanager
def local_server(**config):
    """A dqpose server in this process on a free loopback port, on its own event loop thread
    (``config``: :class:`~dqpose.rpc.server.ServerConfig` fields); yields its address."""
    import asyncio
    import threading

    from dqpose.rpc.server import ServerConfig, start
    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_forever, daemon=True)
    thread.start()
    cfg = ServerConfig(port=0, **config)
    running = asyncio.run_coroutine_threadsafe(start(cfg), loop).result(30)
    try:
        yield f"127.0.0.1:{running.port}"
    finally:
        asyncio.run_coroutine_threadsafe(running.stop(0), loop).result(30)
        loop.call_soon_threadsafe(loop.stop)
        thread.join(10)
