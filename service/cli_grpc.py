"""``dqpose serve | health | blend | interpolate``: the gRPC server and its command-line clients.

Parsers only here; grpc and NumPy are imported when a command runs (``dqpose --help`` stays fast).
"""
from __future__ import annotations

import argparse
import json
import sys

EXIT_ERROR = 2
BLEND_CSV = "x,y,z,qw,qx,qy,qz[,weight]"
INTERPOLATE_CSV = "t,x,y,z,qw,qx,qy,qz"
BLEND_JSON = """\
          {"poses": [{"position": {"x": 0.5, "y": 0, "z": 0.3},
                      "orientation": {"w": 1, "x": 0, "y": 0, "z": 0}}, ...],
           "weights": [1, 2], "method": "dib"}"""
INTERPOLATE_JSON = """\
          {"keyframes": [{"time": 0, "pose": {"position": {"x": 0.5, "y": 0, "z": 0.3},
                                              "orientation": {"w": 1}}}, ...],
           "times": [0, 0.5], "interpolation": "tool_linear"}"""

POSE_FORMATS = """\
input formats (FILE, or - for standard input; chosen by the extension, else sniffed):
  JSON  the request body grpcurl sends (enums as METHOD_DLB or just dlb), e.g.
%s
        positions may also be [x, y, z] and orientations [w, x, y, z]; a bare list of
        %s is accepted too. Missing fields are zero, as in protobuf.
  CSV   one pose per line, columns %s
        (a header line naming the columns is optional; columns are matched by name when present).
units: metres; quaternions scalar first (w, x, y, z), unit norm.
"""


def _connection_args(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("server connection")
    g.add_argument("--target", default="127.0.0.1:50051", help="server address (default: %(default)s)")
    g.add_argument("--token-file", help="file holding the bearer token")
    g.add_argument("--tls-ca", metavar="PEM", help="CA certificate to verify the server (enables TLS)")
    g.add_argument("--tls", action="store_true", help="TLS with the system's root certificates")
    g.add_argument("--cert", metavar="PEM", help="client certificate for mTLS")
    g.add_argument("--key", metavar="PEM", help="client private key for mTLS")
    g.add_argument("--timeout", type=float, default=10.0, help="deadline in seconds (default: %(default)s)")


def add_parser(sub) -> None:
    p = sub.add_parser(
        "serve", help="run the gRPC server",
        description="Serve dqpose.v1.Blending with the gRPC health service and reflection. "
                    "Stops gracefully on SIGTERM/SIGINT: health turns NOT_SERVING, calls in "
                    "flight finish (up to --grace seconds), exit code 0.")
    p.add_argument("--host", default="127.0.0.1", help="address to bind (default: %(default)s)")
    p.add_argument("--port", type=int, default=50051, help="port; 0 picks a free one (default: %(default)s)")
    p.add_argument("--tls-cert", metavar="PEM", help="server certificate chain (enables TLS)")
    p.add_argument("--tls-key", metavar="PEM", help="server private key")
    p.add_argument("--client-ca", metavar="PEM", help="CA for client certificates (requires mTLS)")
    p.add_argument("--token-file", help="file holding a bearer token every call must carry "
                                        "(health stays open); env DQPOSE_TOKEN_FILE also works")
    p.add_argument("--max-message-bytes", type=int, default=4 * 1024 * 1024,
                   help="largest request/response; larger is RESOURCE_EXHAUSTED (default: %(default)s)")
    p.add_argument("--max-poses", type=int, default=10_000,
                   help="most poses, keyframes or times per request (default: %(default)s)")
    p.add_argument("--keepalive", type=float, default=60.0, help="keepalive ping period, s (default: %(default)s)")
    p.add_argument("--grace", type=float, default=10.0, help="shutdown drain time, s (default: %(default)s)")
    p.add_argument("--metrics-port", type=int, help="serve Prometheus metrics on this port")
    p.add_argument("--log-level", default="info", choices=["debug", "info", "warning", "error"],
                   help="JSON log lines on standard error (default: %(default)s)")
    p.add_argument("--no-call-log", action="store_true",
                   help="skip the per-call line (method, status, duration) logged at info")
    p.add_argument("--sims", action="store_true",
                   help="also start the simulated devices (a UR controller, camera views; see "
                        "drivers/sim/fleet.py) and log where they are")
    p.set_defaults(func=_serve)

    p = sub.add_parser("health", help="check a server's gRPC health (exit 0 when SERVING)",
                       description="Ask the grpc.health.v1 service; prints the status and exits 0 "
                                   "when SERVING, 1 otherwise (for HEALTHCHECK and scripts).")
    _connection_args(p)
    p.add_argument("--service", default="", help="service name to check (default: the server)")
    p.set_defaults(func=_health)

    p = sub.add_parser(
        "blend", help="blend poses from a JSON or CSV file",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Blend the poses in FILE into one (on the server at --target, or --local).",
        epilog=POSE_FORMATS % (BLEND_JSON, "poses", BLEND_CSV)
               + "\nexample: dqpose blend --method dlb poses.csv")
    p.add_argument("file", metavar="FILE", help="poses (JSON or CSV; - reads standard input)")
    p.add_argument("--method", choices=["dib", "dlb", "sclerp", "lin", "dec", "log"],
                   help="blending method (default: the file's \"method\", else dib)")
    p.add_argument("--weights", help="comma-separated weights (default: the file's, else equal)")
    p.add_argument("--format", choices=["auto", "csv", "json"], default="auto",
                   help="output format; auto = the input's (default: %(default)s)")
    p.add_argument("--local", action="store_true", help="compute in this process, no server")
    _connection_args(p)
    p.set_defaults(func=_blend)

    p = sub.add_parser(
        "interpolate", help="interpolate between time-stamped keyframes from a JSON or CSV file",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Sample the motion through the keyframes in FILE (on the server at --target, "
                    "or --local). Times outside the keyframe range are an error: the motion is "
                    "never extrapolated.",
        epilog=POSE_FORMATS % (INTERPOLATE_JSON, "keyframes", INTERPOLATE_CSV)
               + "\nexample: dqpose interpolate --step 0.002 --mode tool_linear keyframes.csv")
    p.add_argument("file", metavar="FILE", help="keyframes (JSON or CSV; - reads standard input)")
    p.add_argument("--mode", choices=["screw", "tool_linear"],
                   help="screw: piecewise ScLERP; tool_linear: straight tool path, slerped "
                        "orientation (default: the file's \"interpolation\", else screw)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--times", help="comma-separated sample times, s (default: the file's "
                                   "\"times\", else every --step)")
    g.add_argument("--step", type=float, help="sample period over the whole keyframe range, s "
                                              "(default 0.01); the last keyframe time is included")
    p.add_argument("--format", choices=["auto", "csv", "json"], default="auto",
                   help="output format; auto = the input's (default: %(default)s)")
    p.add_argument("--local", action="store_true", help="compute in this process, no server")
    _connection_args(p)
    p.set_defaults(func=_interpolate)


def _fail(cmd: str, msg: str) -> int:
    print(f"dqpose {cmd}: error: {msg}", file=sys.stderr)
    return EXIT_ERROR


def _read(path: str, mode: str = "rb") -> bytes:
    with open(path, mode) as f:
        return f.read()


def _serve(args) -> int:
    import asyncio
    import contextlib
    import logging
    import os

    from service.server import ServerConfig, serve


    logging.basicConfig(level=args.log_level.upper(), format="%(message)s", stream=sys.stderr)
    calls = logging.getLogger("dqpose.calls")
    if args.no_call_log:
        calls.setLevel(logging.WARNING)
    calls.addHandler(logging.StreamHandler(sys.stderr))
    calls.propagate = False
    token_file = args.token_file or os.environ.get("DQPOSE_TOKEN_FILE")
    try:
        token = _read(token_file, "r").strip() if token_file else None
        if token_file and not token:
            return _fail("serve", f"--token-file: {token_file} is empty")
        cfg = ServerConfig(
            host=args.host, port=args.port,
            tls_cert=_read(args.tls_cert) if args.tls_cert else None,
            tls_key=_read(args.tls_key) if args.tls_key else None,
            client_ca=_read(args.client_ca) if args.client_ca else None,
            token=token, max_message_bytes=args.max_message_bytes, max_poses=args.max_poses,
            keepalive_s=args.keepalive, grace_s=args.grace, metrics_port=args.metrics_port)
        with contextlib.ExitStack() as stack:
            if args.sims:
                from drivers.sim.fleet import Fleet
                for info in stack.enter_context(Fleet()).info:
                    logging.getLogger("dqpose").info(json.dumps({"event": "simulator", **info}))
            try:  # libuv's loop: ~8 % more calls/s with 8 clients, lower p99 (BENCHMARKS.md)
                import uvloop
            except ImportError:
                return asyncio.run(serve(cfg))
            return uvloop.run(serve(cfg))
    except (OSError, ValueError) as e:
        return _fail("serve", str(e))


def _client(args):
    from service.client import Client

    token = _read(args.token_file, "r").strip() if args.token_file else None
    return Client(args.target, token=token, tls=args.tls,
                  root_certificates=_read(args.tls_ca) if args.tls_ca else None,
                  certificate_chain=_read(args.cert) if args.cert else None,
                  private_key=_read(args.key) if args.key else None, timeout=args.timeout)


def _rpc_failure(cmd: str, args, e) -> int:
    import grpc

    if e.code() in (grpc.StatusCode.UNAVAILABLE, grpc.StatusCode.DEADLINE_EXCEEDED):
        return _fail(cmd, f"no answer from the server at {args.target} ({e.code().name}: "
                          f"{e.details()}); start one with `dqpose serve`, or add --local")
    return _fail(cmd, f"{e.code().name}: {e.details()}")


def _health(args) -> int:
    import grpc

    try:
        with _client(args) as c:
            status = c.health(args.service)
    except OSError as e:
        return _fail("health", str(e))
    except grpc.RpcError as e:
        print(f"dqpose health: {args.target}: {e.code().name}", file=sys.stderr)
        return 1
    print(status)
    return 0 if status == "SERVING" else 1


def _blend(args) -> int:
    import grpc

    from service import posefile as io
    from service import dq

    try:
        req = io.read_blend(args.file)
        method = args.method or req.method or "dib"
        weights = io.parse_floats("--weights", args.weights) if args.weights else req.weights
        fmt = req.format if args.format == "auto" else args.format
        if args.local:
            info = dq.dib(req.dqs, weights, return_info=True) if method == "dib" else None
            mean = info.mean if info else dq.blend(req.dqs, weights, method)
            iterations, residual = (int(info.iterations), float(info.residual)) if info else (0, 0.0)
        else:
            with _client(args) as c:
                mean, iterations, residual = c.blend(req.dqs, weights, method, return_info=True)
    except (OSError, ValueError) as e:
        return _fail("blend", str(e))
    except grpc.RpcError as e:
        return _rpc_failure("blend", args, e)
    sys.stdout.write(io.format_blend(mean, iterations, residual, fmt))
    return 0


def _interpolate(args) -> int:
    import grpc

    from service import posefile as io
    from service.interpolate import interpolate

    try:
        req = io.read_interpolate(args.file)
        mode = args.mode or req.mode or "screw"
        if args.times:
            times = io.parse_floats("--times", args.times)
        elif args.step is None and req.times is not None:
            times = req.times
        else:
            times = io.sample_times(req.times_k, 0.01 if args.step is None else args.step)
        fmt = req.format if args.format == "auto" else args.format
        if args.local:
            out = interpolate(req.times_k, req.dqs_k, times, mode)
        else:
            with _client(args) as c:
                out = c.interpolate(req.times_k, req.dqs_k, times, mode)
    except (OSError, ValueError) as e:
        return _fail("interpolate", str(e))
    except grpc.RpcError as e:
        return _rpc_failure("interpolate", args, e)
    sys.stdout.write(io.format_samples(times, out, fmt))
    return 0
