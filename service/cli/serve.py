"""``dqpose serve`` (the gRPC server, optionally with the simulated devices beside it) and
``dqpose health`` (ask a server's health service)."""
from __future__ import annotations

import argparse
import gc
import json
import os
import sys
import textwrap

from dqpose import limits
from dqpose.cli.common import client, connection_args, fail, missing_extra, open_arm, read
from dqpose.rpc import DEFAULT_MAX_MESSAGE_BYTES, DEFAULT_MAX_POSES

# The worker pool is the server's parallelism (limits.workers): OpenBLAS's own threads beside
# each worker oversubscribe the cores and spin while idle (a 100-measurement acceleration_psd
# fit took 201 ms of CPU on two BLAS threads, 42 ms on one, on a loaded 2-core machine). Set
# before NumPy's first import, which nothing above makes.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


def configure(name: str, p) -> None:
    if name == "serve":
        from dqpose.rpc.server import INTERRUPT_GRACE, SERVICERS
        p.formatter_class = argparse.RawDescriptionHelpFormatter
        p.description = textwrap.fill(
            f"Serve {', '.join(s.NAME for s in SERVICERS)} with the gRPC health service and "
            "reflection. Stops gracefully on SIGTERM: health turns NOT_SERVING and new "
            "calls are UNAVAILABLE at once, the listener closes --drain seconds later, calls in "
            "flight get --grace seconds more to finish (an arm's plan that cannot end by then "
            "is brought to a controlled stop at once); exit code 0. On SIGINT (Ctrl-C) the "
            f"same without the drain and with a grace of {INTERRUPT_GRACE:g} s at most; a "
            "second Ctrl-C ends it at once (exit code 130).", 79)
        p.epilog = _arm_keys_help()
        p.add_argument("--host", default="127.0.0.1",
                       help="address to bind (default: %(default)s)")
        p.add_argument("--port", type=int, default=50051,
                       help="port; 0 picks a free one (default: %(default)s)")
        p.add_argument("--tls-cert", metavar="PEM", help="server certificate chain (enables TLS)")
        p.add_argument("--tls-key", metavar="PEM", help="server private key")
        p.add_argument("--client-ca", metavar="PEM",
                       help="CA for client certificates (requires mTLS)")
        p.add_argument("--token-file", help="file holding a bearer token every call must carry "
                                            "(health stays open); env DQPOSE_TOKEN_FILE also works")
        p.add_argument("--max-message-bytes", type=int, default=DEFAULT_MAX_MESSAGE_BYTES,
                       help="largest request/response; larger is RESOURCE_EXHAUSTED "
                            "(default: %(default)s)")
        p.add_argument("--max-poses", type=int, default=DEFAULT_MAX_POSES,
                       help="most poses, keyframes or times per request (default: %(default)s)")
        limits.add_flags(p.add_argument_group(
            "limits", "what one request or stream may cost (the cost model: service/limits.py); "
                      "a request over one is refused RESOURCE_EXHAUSTED naming it"))
        p.add_argument("--keepalive", type=float, default=60.0,
                       help="keepalive ping period, s (default: %(default)s)")
        p.add_argument("--drain", type=float, default=0.5,
                       help="after SIGTERM, how long health answers NOT_SERVING (and new calls "
                            "UNAVAILABLE) before the listener closes, so that load balancers "
                            "polling health see it; with 0 a call that arrives as it closes may "
                            "be CANCELLED by gRPC, s (default: %(default)s)")
        p.add_argument("--grace", type=float, default=10.0,
                       help="once the listener closed, how long calls in flight get to finish "
                            "before they are cancelled, s (default: %(default)s)")
        p.add_argument("--metrics-port", type=int,
                       help="serve Prometheus metrics on this port (with --token-file, a scrape "
                            "sends 'Authorization: Bearer <token>')")
        p.add_argument("--metrics-host", default="127.0.0.1",
                       help="address the metrics port binds (default: %(default)s)")
        p.add_argument("--replica-name", metavar="NAME",
                       help="the name every answer carries in its x-dqpose-replica metadata, "
                            "for clients behind a load balancer (default: the host name)")
        p.add_argument("--log-level", default="info", choices=["debug", "info", "warning", "error"],
                       help="JSON log lines on standard error (default: %(default)s)")
        p.add_argument("--no-call-log", action="store_true",
                       help="skip the per-call line (method, status, duration) logged at info")
        _arm_args(p)
        _recording_args(p)
        p.add_argument("--sims", action="store_true",
                       help="also start the simulated devices (a UR controller, a PiPER, camera "
                            "views; see drivers/sim/fleet.py), log where they are and serve the "
                            "simulated arms as ur=ur:sim and piper=piper:sim; with --arm, only "
                            "the arms given (--arm NAME=KIND:sim drives a simulator)")
        p.set_defaults(func=_serve)
    else:
        p.description = ("Ask the grpc.health.v1 service; prints the status and exits 0 when "
                         "SERVING, 1 otherwise (for HEALTHCHECK and scripts).")
        connection_args(p)
        p.add_argument("--service", default="", help="service name to check (default: the server)")
        p.set_defaults(func=_health)


def _arm_args(p) -> None:
    """The arms Execute may drive and where their control loops run."""
    from dqpose.drivers.spec import GRAMMAR as ARM_GRAMMAR
    p.add_argument("--arm", action="append", default=[], metavar="NAME=SPEC",
                   help="an arm Trajectories.Execute may drive, by name, as "
                        f"NAME={ARM_GRAMMAR}: e.g. ur=ur:192.168.1.10?stale_after=0.3, "
                        "piper=piper:socketcan:can0; TARGET 'sim' is that kind's simulator "
                        "started by --sims (ur=ur:sim, piper=piper:sim?max_tracking=0.003); "
                        "the keys are listed below. Repeat for more arms. Each is connected "
                        "at start and stopped when the server stops.")
    p.add_argument("--arm-realtime", type=int, metavar="PRIO",
                   help="run each arm's control loop with real-time scheduling (Linux "
                        "SCHED_FIFO at PRIO, 1..99; needs CAP_SYS_NICE): fewer late "
                        "set-points on a busy machine (default: ordinary scheduling)")
    p.add_argument("--arm-loop", choices=["auto", "process", "thread"], default="auto",
                   help="where each arm's Execute control loop runs: 'process', the arm "
                        "opened in a process of its own, so no work of the server's delays "
                        "a set-point (needs x86-64 and a bus that reaches across processes, "
                        "not python-can's virtual); 'thread', in the server; 'auto' "
                        "(default): the arm's process where it can, else a thread (logged)")


def _recording_args(p) -> None:
    """Recording into MCAP files and serving it live."""
    rec = p.add_argument_group(
        "recording", "every Fuse and StreamFuse call into MCAP files (docs/recording.md; "
                     "the [record] extra); `dqpose replay FILE` replays one")
    rec.add_argument("--record", metavar="DIR",
                     help="record into DIR (created if missing), a new file at either bound "
                          "below")
    rec.add_argument("--live", metavar="HOST:PORT", nargs="?", const="",
                     help="serve the recording's channels live on a Foxglove WebSocket "
                          "(Foxglove or Lichtblick: open connection, Foxglove WebSocket, "
                          "ws://HOST:PORT; default 127.0.0.1:8765; README), with or without "
                          "--record; with --token-file a client connects to "
                          "ws://HOST:PORT/?token=TOKEN, and beyond the loopback it needs "
                          "--token-file or --live-insecure")
    rec.add_argument("--live-origin", metavar="ORIGIN", action="append", default=[],
                     help="a browser origin --live lets in (e.g. https://app.foxglove.dev); "
                          "repeat for more; a client that sends another Origin is refused, "
                          "one that sends none is let in (default: none)")
    rec.add_argument("--live-insecure", action="store_true",
                     help="--live lets in every client that reaches it: no token asked, no "
                          "origin checked")
    rec.add_argument("--record-max-mb", type=float, default=256.0,
                     help="a new file after this many MB (default: %(default)s)")
    rec.add_argument("--record-max-s", type=float, default=3600.0,
                     help="a new file after this many seconds (default: %(default)s)")
    rec.add_argument("--record-rate", type=float, default=30.0,
                     help="every body of a world is recorded at this rate, Hz of its "
                          "measurement time, subscribed or not (the recorder's own "
                          "subscriber: a Subscribe call marked internal; default: "
                          "%(default)s)")
    rec.add_argument("--record-queue", type=int, default=100_000,
                     help="messages waiting for the disk at most; beyond, they are dropped "
                          "(counted, logged, marked in the file), never an RPC delayed "
                          "(default: %(default)s)")


#: the TARGET that stands for the simulator of the arm's kind (drivers.sim.fleet)
SIM = "sim"


def sim_arms(fleet) -> list[str]:
    """The ``--arm`` values ``--sims`` stands for when none is given: each simulated arm that
    started, named by its kind (``ur=ur:sim``, ``piper=piper:sim``)."""
    started = {i["device"] for i in fleet.info if "error" not in i}
    return [f"{kind}={kind}:{SIM}" for kind in ("ur", "piper") if kind in started]


def _log_sims(fleet, arm_specs: dict) -> None:
    """A line per simulated device: where it is and how to use it; one the server drives as an
    arm is used through the server (its controller takes one client: ours)."""
    import logging
    served = {spec.kind: name for name, (_, spec) in arm_specs.items() if spec.target == SIM}
    for info in fleet.info:
        if info["device"] in served:
            name = served[info["device"]]
            info = {**info, "arm": name, "use": f"dqpose arm get {name}; Client.get_arm({name!r})"}
        logging.getLogger("dqpose").info(json.dumps({"event": "simulator", **info}))


def _arm_keys_help() -> str:
    """drivers.ARM_KEYS, one wrapped line each."""
    from dqpose.drivers.spec import key_table
    lines = [textwrap.fill(line, 79, initial_indent="  ", subsequent_indent="      ")
             for line in key_table().splitlines()]
    return "arm spec keys (--arm NAME=KIND:TARGET?key=value&key=value):\n" + "\n".join(lines)


def _serve(args) -> int:
    import asyncio
    import contextlib
    import logging
    import os

    from dqpose.rpc.server import ConfigError, ServerConfig, serve

    logging.basicConfig(level=args.log_level.upper(), format="%(message)s", stream=sys.stderr)
    calls = logging.getLogger("dqpose.calls")
    if args.no_call_log:
        calls.setLevel(logging.WARNING)
    calls.addHandler(logging.StreamHandler(sys.stderr))
    calls.propagate = False
    token_file = args.token_file or os.environ.get("DQPOSE_TOKEN_FILE")
    try:
        token = read(token_file, "r").strip() if token_file else None
        if token_file and not token:
            return fail("serve", f"--token-file: {token_file} is empty")
        arm_specs = _arm_specs(args.arm)
        if args.arm_realtime is not None and not 1 <= args.arm_realtime <= 99:
            return fail("serve", f"--arm-realtime: must be within 1..99, got {args.arm_realtime}")
        cfg = ServerConfig(
            host=args.host, port=args.port,
            tls_cert=read(args.tls_cert) if args.tls_cert else None,
            tls_key=read(args.tls_key) if args.tls_key else None,
            client_ca=read(args.client_ca) if args.client_ca else None,
            token=token, max_message_bytes=args.max_message_bytes, max_poses=args.max_poses,
            keepalive_s=args.keepalive, grace_s=args.grace, drain_s=args.drain,
            metrics_port=args.metrics_port, metrics_host=args.metrics_host,
            limits=limits.from_args(args),
            **({"replica_name": args.replica_name} if args.replica_name is not None else {}))
        simulated = [f"{n}={text}" for n, (text, spec) in arm_specs.items() if spec.target == SIM]
        if simulated and not args.sims:
            return fail("serve", f"--arm {simulated[0]}: TARGET '{SIM}' is the simulator that "
                                 f"--sims starts; add --sims")
        with contextlib.ExitStack() as stack:
            if (args.record is not None or args.live is not None) and (
                    code := _open_recorder(args, cfg, stack)):
                return code
            fleet = None
            if args.sims:
                from dqpose.drivers.sim.fleet import Fleet
                try:
                    fleet = stack.enter_context(Fleet())
                except ModuleNotFoundError as e:
                    return missing_extra("serve --sims", e)
                arm_specs = arm_specs or _arm_specs(sim_arms(fleet))
                _log_sims(fleet, arm_specs)
            if arm_specs and (code := _open_arms(args, arm_specs, cfg, fleet, stack)):
                return code
            # libuv's loop: ~8 % more calls/s with 8 clients
            # (docs/benchmarks/grpc.md#server-choices-measured)
            try:
                import uvloop
            except ImportError:
                uvloop = None
            # what the server is made of lives as long as it does: left out of every collection,
            # the idle one the worker pool runs (service/rpc/calls.py) takes ~2 ms, not ~30
            gc.freeze()
            return asyncio.run(serve(cfg)) if uvloop is None else uvloop.run(serve(cfg))
    except ConfigError as e:
        path = getattr(args, e.setting, None) if e.setting in PEM_FLAGS else None
        return fail("serve", f"{_flag(e.setting)}{f' {path}' if path else ''}: {e.problem}")
    except (OSError, ValueError) as e:
        setting = getattr(e, "setting", None)    # server.AddressInUse: which flag to change
        hint = f"; choose another {_flag(setting)}" if setting else ""
        return fail("serve", f"{e}{hint}")


def _open_recorder(args, cfg, stack) -> int | None:
    """``--record``/``--live``: the recorder into ``cfg``, closed by ``stack``; an exit code
    when it cannot start."""
    from dqpose.errors import MissingExtra
    from dqpose.record import LiveFailed, open_recorder, parse_address
    try:
        live = None if args.live is None else parse_address(args.live)
    except ValueError as e:
        return fail("serve", str(e))
    cmd = "serve --record" if args.record is not None else "serve --live"
    for flag, value in (("--record-max-mb", args.record_max_mb),
                        ("--record-max-s", args.record_max_s),
                        ("--record-queue", args.record_queue),
                        ("--record-rate", args.record_rate)):
        if not value > 0:
            return fail("serve", f"{flag}: must be > 0, got {value:g}")
    if args.record_rate > cfg.limits.max_output_rate:
        return fail("serve", "--record-rate: " + limits.over_text(
            f"{args.record_rate:g} Hz", "max_output_rate", cfg.limits.max_output_rate))
    try:
        cfg.recorder = open_recorder(
            args.record, max_bytes=max(1, int(args.record_max_mb * 1e6)),
            max_seconds=args.record_max_s, queue=args.record_queue, live=live,
            live_token=cfg.token, live_origins=args.live_origin,
            live_insecure=args.live_insecure, world_rate=args.record_rate)
    except MissingExtra as e:
        return missing_extra(cmd, e)
    except (LiveFailed, ValueError) as e:
        return fail("serve", str(e))
    except OSError as e:
        return fail("serve", f"--record {args.record}: {e.strerror or e}")
    stack.callback(cfg.recorder.close)
    return None


def _open_arms(args, arm_specs: dict, cfg, fleet, stack) -> int | None:
    """``--arm``: each arm opened into ``cfg.arms`` (a simulated one on ``fleet``), closed by
    ``stack``, and the executor; an exit code when one cannot open."""
    import dataclasses
    import functools
    import logging

    try:
        from dqpose import drivers
        from dqpose.drivers.executor import Executor
    except ModuleNotFoundError as e:
        return missing_extra("serve --arm", e)
    for name, (text, spec) in arm_specs.items():
        try:
            simulated = spec.target == SIM
            if simulated:
                spec = dataclasses.replace(spec, target=fleet.target(spec.kind))
            # the server's own work delays a control thread's set-points (1,991 missed
            # cycles in 30 s against 51:
            # docs/benchmarks/arms.md#thread-or-process-for-the-loop)
            why_not = None if args.arm_loop == "process" else (
                "--arm-loop thread" if args.arm_loop == "thread"
                else drivers.process_problem(str(spec)))
            cfg.arms[name] = stack.enter_context(
                open_arm(spec, process=why_not is None, simulated=simulated))
        except ModuleNotFoundError as e:
            return missing_extra("serve --arm", e)
        except (OSError, ValueError, RuntimeError) as e:
            return fail("serve", f"--arm {name}={text}: {e}")
        logging.getLogger("dqpose").info(json.dumps(
            {"event": "arm", "name": name, "spec": str(spec),
             "loop": "thread" if why_not else "process",
             **({"why": why_not} if why_not else {})}))
    cfg.executor = functools.partial(Executor, realtime=args.arm_realtime)
    return None


def _arm_specs(values: list[str]) -> dict:
    """``--arm NAME=SPEC`` values by name, each ``(the text, drivers.ArmSpec)``; ValueError
    naming the flag for a malformed or repeated one."""
    from dqpose.drivers.spec import GRAMMAR, parse_arm_spec
    out: dict = {}
    for v in values:
        name, sep, spec = v.partition("=")
        if not sep or not name or not spec:
            raise ValueError(f"--arm: expected NAME={GRAMMAR} (e.g. ur=ur:192.168.1.10), "
                             f"got {v!r}")
        if not name.isidentifier():
            raise ValueError(f"--arm: the name {name!r} must be a word (letters, digits, _)")
        if name in out:
            raise ValueError(f"--arm: {name!r} is given twice")
        try:
            out[name] = (spec, parse_arm_spec(spec))
        except ValueError as e:
            raise ValueError(f"--arm {v}: {e}") from None
    return out


# ServerConfig fields whose flag is not the field's name with dashes; PEM_FLAGS name files
FLAGS = {"keepalive_s": "--keepalive", "grace_s": "--grace", "drain_s": "--drain",
         "token": "--token-file"}
PEM_FLAGS = ("tls_cert", "tls_key", "client_ca")


def _flag(setting: str) -> str:
    """The ``dqpose serve`` flag that sets the ServerConfig field ``setting``."""
    return FLAGS.get(setting, "--" + setting.replace("_", "-"))


def _health(args) -> int:
    from dqpose.rpc.client import RpcError

    try:
        with client(args) as c:
            status = c.health(args.service)
    except OSError as e:
        return fail("health", str(e))
    except RpcError as e:
        print(f"dqpose health: {args.server}: {e.code.name}", file=sys.stderr)
        return 1
    print(status)
    return 0 if status == "SERVING" else 1
