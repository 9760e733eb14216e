"""``dqpose world``: a server's shared world (the ``dqpose.v1.World`` service): ``publish FILE``
replays a recorded measurement file into it (the file ``dqpose fuse`` reads), ``watch BODY...``
shows a live table of fused poses, ``lookup TARGET SOURCE`` prints one relative pose."""
from __future__ import annotations

import argparse
import math
import sys

from dqpose.cli.common import client, connection_args, failure

EPILOG = """\
publish: FILE is what `dqpose fuse` reads (JSON/YAML FuseRequest, or CSV); every measurement
  needs a body (the file's, else --body). The file's options.sources (when it has any) are
  configured into the world first unless --no-configure. Measurements are sent in file order,
  --batch per request, numbered from 1 under --producer; the acks' errors are printed.
watch: one line per answer: body, time, position (m), rotation vector (deg), the standard
  deviations of position (mm) and rotation (deg), the sources' NIS verdicts and the estimated
  latencies. Ctrl-C ends it.
lookup: T_target_source (tf2's lookupTransform order; "" or "world" is the world frame) at
  --time (0: the newest time both are known at), with its covariance.
"""


def configure(name: str, p) -> None:
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.description = ("A server's shared world: many producers publish measurements of bodies "
                     "into it, many consumers read fused poses and relative poses out.")
    p.epilog = EPILOG
    sub = p.add_subparsers(dest="action", required=True, metavar="ACTION")
    pub = sub.add_parser("publish", help="replay a recorded measurement file into the world")
    pub.add_argument("file", metavar="FILE", help="measurements (JSON, YAML or CSV; - stdin)")
    pub.add_argument("--body", default="", help="the body of measurements that name none")
    pub.add_argument("--producer", default="dqpose-world-publish",
                     help="the producer name the acks are kept under (default: %(default)s)")
    pub.add_argument("--batch", type=int, default=50,
                     help="measurements per request (default: %(default)s)")
    pub.add_argument("--no-configure", action="store_true",
                     help="do not configure the file's options.sources into the world")
    watch = sub.add_parser("watch", help="a live table of fused poses")
    watch.add_argument("bodies", nargs="*", metavar="BODY", help="bodies (none: all)")
    watch.add_argument("--rate", type=float, default=0.0,
                       help="answers per second of measurement time per body (0: every update)")
    watch.add_argument("--relative-to", default="", help="a body the poses are relative to")
    watch.add_argument("--count", type=int, default=0,
                       help="stop after this many answers (0: until Ctrl-C)")
    look = sub.add_parser("lookup", help="the pose of SOURCE in TARGET's frame")
    look.add_argument("frame_target", metavar="TARGET", help="a body, or world")
    look.add_argument("frame_source", metavar="SOURCE", help="a body, or world")
    look.add_argument("--time", type=float, default=0.0,
                      help="measurement time, s (0: the newest both are known at)")
    for q in (pub, watch, look):
        connection_args(q, target_alias=q is not look)
        q.add_argument("--world", default="", metavar="NAME",
                       help="the named world on the server (x-dqpose-world; default: the "
                            "server's default world)")
    p.set_defaults(func=_run)


def _frame(name: str) -> str:
    return "" if name == "world" else name


def _run(args) -> int:
    try:
        return {"publish": _publish, "watch": _watch, "lookup": _lookup}[args.action](args)
    except KeyboardInterrupt:
        return 130
    except Exception as e:
        return failure(f"world {args.action}", args, e)


def publish_requests(path: str, body: str, batch: int, producer: str):
    """``(sources, PublishRequest s)`` of a measurement file: its options' sources and its
    measurements in file order, ``batch`` per request, numbered from 1."""
    from dqpose.cli.fuse import read_request
    from dqpose.rpc._proto.dqpose.v1 import world_pb2 as wpb

    if batch < 1:
        raise ValueError(f"--batch: must be at least 1, got {batch}")
    request = read_request(path)
    ms = list(request.measurements)
    for i, m in enumerate(ms):
        if not m.body:
            if not body:
                raise ValueError(f"{path}: measurements[{i}].body: none given; name it in the "
                                 f"file or with --body")
            m.body = body
    return list(request.options.sources), [
        wpb.PublishRequest(measurements=ms[k:k + batch], producer=producer,
                           sequence=k // batch + 1) for k in range(0, len(ms), batch)]


def _publish(args) -> int:
    from dqpose.rpc.fusion_convert import sources_from_msg

    sources, requests = publish_requests(args.file, args.body, args.batch, args.producer)
    with client(args) as c:
        if sources and not args.no_configure:
            c.configure_world(sources_from_msg(sources, f"{args.file}: options.sources"))
        errors, last = 0, 0
        for ack in c.publish_requests(requests):
            last = ack.acked_through
            for _, _, details in ack.errors:
                errors += 1
                print(f"error: {details}", file=sys.stderr)
    n = sum(len(r.measurements) for r in requests)
    print(f"published {n} measurements in {len(requests)} requests as {args.producer!r}: "
          f"acked through {last}, {errors} errors")
    return 1 if errors else 0


HEADER = (f"{'body':>12} {'time s':>10} {'x m':>8} {'y m':>8} {'z m':>8} {'rot deg':>18} "
          f"{'σpos mm':>8} {'σrot deg':>8}  NIS verdicts / latencies")


def format_row(a) -> str:
    """One :class:`~dqpose.rpc.client_types.StreamAnswer` as a line of the watch table."""
    import numpy as np

    from dqpose import dq, fusion, lie

    if a.fused is None:
        return f"{a.body:>12} {a.time:10.4f}  error: {a.error}"
    f = a.fused
    _, t = dq.to_pose(f.mean)
    w = np.degrees(lie.se3_log(f.mean)[:3])
    sd = np.sqrt(np.maximum(np.diag(f.covariance), 0.0))
    verdicts = " ".join(f"{s.name}:{fusion.Verdict(s.verdict).name.lower()}"
                        for s in f.sources)
    lat = " ".join(f"{x.name}={x.value * 1e3:.1f}ms" for x in f.latencies)
    return (f"{a.body:>12} {a.time:10.4f} {t[0]:8.4f} {t[1]:8.4f} {t[2]:8.4f} "
            f"{w[0]:+6.2f},{w[1]:+6.2f},{w[2]:+6.2f} {np.linalg.norm(sd[3:]) * 1e3:8.3f} "
            f"{math.degrees(np.linalg.norm(sd[:3])):8.4f}  {verdicts} {lat}".rstrip())


def _watch(args) -> int:
    with client(args) as c:
        print(HEADER)
        for k, a in enumerate(c.subscribe(args.bodies, args.rate, args.relative_to), 1):
            print(format_row(a), flush=True)
            if args.count and k >= args.count:
                break
    return 0


def _lookup(args) -> int:
    import numpy as np

    from dqpose import dq

    with client(args) as c:
        r = c.lookup(_frame(args.frame_target), _frame(args.frame_source), args.time)
    q, t = dq.to_pose(r.pose)
    if q[0] < 0:
        q = -q
    print(f"T_{args.frame_target}_{args.frame_source} at {r.time:.9g} s (x,y,z,qw,qx,qy,qz):")
    print("  " + ",".join(f"{v:.9g}" for v in (*t, *q)))
    print("covariance (rotation first [wx wy wz vx vy vz], right perturbation):")
    for row in np.asarray(r.covariance):
        print("  " + " ".join(f"{v: .6e}" for v in row))
    return 0
