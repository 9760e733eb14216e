"""``dqpose world``: a server's shared world (the ``dqpose.v1.World`` service): ``publish FILE``
replays a recorded measurement file into it (the file ``dqpose fuse`` reads), ``watch BODY...``
shows a live table of fused poses, ``lookup TARGET SOURCE`` prints one relative pose, ``frames``
prints the frame tree."""
from __future__ import annotations

import argparse
import sys

from dqpose.cli.common import client, connection_args, failure
from dqpose.cli.inputs import add_quaternion_order

EPILOG = """\
publish: FILE is what `dqpose fuse` reads (JSON/YAML FuseRequest, or CSV); every measurement
  needs a body (the file's, else --body). The file's options.sources (when it has any) are
  configured into the world first unless --no-configure. Measurements are sent in file order,
  --batch per request, numbered from 1 under --producer; the acks' errors are printed.
watch: one line per answer: the time in s since the first answer's, the body, its position
  (mm), rotation vector (axis times angle) and roll, pitch, yaw (deg; fixed axes as ROS has them:
  R = Rz(yaw) Ry(pitch) Rx(roll)), each angle unwrapped against the body's row before, one sigma
  of position (mm) and rotation (deg) along the least certain direction, then the sources' NIS
  verdicts in name order and the latencies the world estimates. Ctrl-C ends it.
lookup: T_target_source (tf2's lookupTransform order; "" or "world" is the world frame) at
  --at (alias --time; 0: the newest time both are known at): position, rotation, one sigma as
  watch has them. --source-time: the source at that time through --fixed-frame (tf2's advanced
  lookupTransform); --wait S: wait up to S s for the data (tf2's waitForTransform).
frames: the frame tree as tf2_tools' view_frames has it, one line a frame: "parent -> child",
  its kind, rate (measurements a second of measurement time over the second before its newest),
  span of kept measurements (s) and the sources that measured it; children under their parent.
--json: one JSON object per answer (watch: a line each) with SI units, absolute times, the pose
  with named components (as the pose files have it) and the 6x6 covariance (rotation first).
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
    add_quaternion_order(pub)
    watch = sub.add_parser("watch", help="a live table of fused poses")
    watch.add_argument("bodies", nargs="*", metavar="BODY", help="bodies (none: all)")
    watch.add_argument("--rate", type=float, default=0.0,
                       help="answers per second of measurement time per body (0: every update)")
    watch.add_argument("--relative-to", default="", help="a body the poses are relative to")
    watch.add_argument("--count", type=int, default=0,
                       help="stop after this many answers (0: until Ctrl-C)")
    look = sub.add_parser("lookup", help="the pose of SOURCE in TARGET's frame")
    look.add_argument("frame_target", metavar="TARGET", help="a frame (world frames), or world")
    look.add_argument("frame_source", metavar="SOURCE", help="a frame (world frames), or world")
    look.add_argument("--at", "--time", dest="time", type=float, default=0.0, metavar="S",
                      help="measurement time, s (0: the newest both are known at)")
    look.add_argument("--source-time", type=float, default=0.0, metavar="S",
                      help="SOURCE at this time, TARGET at --at, through --fixed-frame "
                           "(tf2's advanced lookup; 0: --at's)")
    look.add_argument("--fixed-frame", default="", metavar="FRAME",
                      help="the frame held still between the two times (default: world)")
    look.add_argument("--wait", type=float, default=0.0, metavar="S",
                      help="wait up to S seconds (at most 10) for the world to be able to "
                           "answer (tf2's waitForTransform)")
    frames = sub.add_parser("frames", help="the frame tree: parent -> child, kind, rate, span")
    for q in (watch, look, frames):
        q.add_argument("--json", action="store_true",
                       help="for machines: JSON, SI units, the pose's components named")
    for q in (pub, watch, look, frames):
        connection_args(q, target_alias=q is not look)
        q.add_argument("--world", default="", metavar="NAME",
                       help="the named world on the server (x-dqpose-world; default: the "
                            "server's default world)")
    p.set_defaults(func=_run)


def _frame(name: str) -> str:
    return "" if name == "world" else name


def _run(args) -> int:
    try:
        return {"publish": _publish, "watch": _watch, "lookup": _lookup,
                "frames": _frames}[args.action](args)
    except KeyboardInterrupt:
        return 130
    except Exception as e:
        return failure(f"world {args.action}", args, e)


def publish_requests(path: str, body: str, batch: int, producer: str, order: str | None = None):
    """``(sources, PublishRequest s)`` of a measurement file: its options' sources and its
    measurements in file order, ``batch`` per request, numbered from 1; ``order``
    (``--quaternion-order``) of quaternions not named one by one."""
    from dqpose.cli.fuse import read_request
    from dqpose.rpc._proto.dqpose.v1 import world_pb2 as wpb

    if batch < 1:
        raise ValueError(f"--batch: must be at least 1, got {batch}")
    request = read_request(path, order)
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

    sources, requests = publish_requests(args.file, args.body, args.batch, args.producer,
                                         args.quaternion_order)
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


def _watch(args) -> int:
    from dqpose.cli.readout import Readout, answer_json

    table = Readout()
    with client(args) as c:
        if not args.json:
            print(table.header())
        for k, a in enumerate(c.subscribe(args.bodies, args.rate, args.relative_to), 1):
            print(answer_json(a) if args.json else table.row(a), flush=True)
            if args.count and k >= args.count:
                break
    return 0


def _lookup(args) -> int:
    from dqpose.cli.readout import lookup_json, lookup_text

    with client(args) as c:
        r = c.lookup(_frame(args.frame_target), _frame(args.frame_source), args.time,
                     wait=args.wait, source_time=args.source_time,
                     fixed_frame=_frame(args.fixed_frame))
    if args.json:
        sys.stdout.write(lookup_json(args.frame_target, args.frame_source, r))
    else:
        head, rest = lookup_text(args.frame_target, args.frame_source, r).split("\n", 1)
        if args.source_time:    # the source at its own time, under the header
            head += (f"\n  source at       {args.source_time:.9g} s, through "
                     f"{args.fixed_frame or 'world'} held still")
        sys.stdout.write(head + "\n" + rest)
    return 0


def _frames(args) -> int:
    import json

    with client(args) as c:
        frames = c.frames()
    if args.json:
        print(json.dumps([{"name": f.name, "parent": f.parent, "kind": _kind(f.kind),
                           "oldest": f.oldest, "newest": f.newest, "rate_hz": f.rate_hz,
                           "sources": list(f.sources)} for f in frames], indent=1))
    else:
        sys.stdout.write(frames_text(frames))
    return 0


def _kind(kind) -> str:
    return getattr(kind, "name", str(kind)).lower().replace("_", " ")


def frames_text(frames) -> str:
    """The tree of :class:`dqpose.frames.FrameInfo` s, depth first from the world ("world"),
    one line a frame (a frame whose parent is not listed, a body not measured yet, under it)."""
    children: dict[str, list] = {}
    names = {f.name for f in frames}
    for f in frames:
        if f.name:
            children.setdefault(f.parent if f.parent in names else "", []).append(f)
    lines: list[str] = []

    def walk(parent: str, depth: int) -> None:
        for f in children.get(parent, ()):
            what = [_kind(f.kind)]
            if f.newest or f.oldest:
                # as tf2's view_frames: the rate, the buffer's length, the newest's time
                what += [f"{f.rate_hz:g} Hz", f"{f.newest - f.oldest:.3f} s kept",
                         f"newest {f.newest:.3f} s"]
            if f.sources:
                what.append("sources " + ", ".join(f.sources))
            lines.append(f"{'  ' * depth}{f.parent or 'world'} -> {f.name}: {'; '.join(what)}")
            walk(f.name, depth + 1)

    walk("", 0)
    return "world\n" + "".join(line + "\n" for line in lines)
