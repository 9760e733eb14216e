"""``dqpose blend`` and ``dqpose interpolate``: poses from a JSON, YAML or CSV file (read by
:mod:`dqpose.cli.posefile`), computed on a server or ``--local``ly, printed as CSV or JSON."""
from __future__ import annotations

import argparse
import sys

from dqpose.cli.common import client, connection_args, failure
from dqpose.cli.inputs import add_quaternion_order

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
input formats (FILE, or - for standard input; chosen by the extension, else by the content):
  JSON  the request body grpcurl sends (enums as METHOD_DLB or just dlb), e.g.
%s
        positions may also be [x, y, z]; an orientation as four numbers names their order:
        "orientation_xyzw": [x, y, z, w] (ROS, Eigen, scipy) or "orientation_wxyz": [w, x, y, z]
        (a bare "orientation": [...] is refused unless --quaternion-order names it). A bare
        list of %s is accepted too. A missing position or coordinate is zero, as in
        protobuf; an orientation is required, and a key not shown here is an error.
  YAML  the same document in YAML (.yaml, .yml; needs the [yaml] extra).
  CSV   one pose per line, columns %s, separated by commas, semicolons,
        tabs or spaces; a header line names the columns (matched by name, any order: qx,qy,qz,qw
        works too); a file without one needs --quaternion-order.
units: metres; quaternions of unit norm (within 1e-3: normalised).
"""


def configure(name: str, p) -> None:
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    if name == "blend":
        from dqpose.dq import METHODS  # NumPy and the C core: only for this command's help

        methods = "".join(f"  {m:8s}{spec.description}\n" for m, spec in METHODS.items())
        p.description = "Blend the poses in FILE into one (on the server at --server, or --local)."
        p.epilog = (POSE_FORMATS % (BLEND_JSON, "poses", BLEND_CSV)
                    + "\nmethods (--method):\n" + methods
                    + "\nexample: dqpose blend --method dlb poses.csv")
        p.add_argument("file", metavar="FILE",
                       help="poses (JSON, YAML or CSV; - reads standard input)")
        p.add_argument("--method", choices=list(METHODS),
                       help="blending method, see below (default: the file's \"method\", "
                            "else dib)")
        p.add_argument("--weights",
                       help="comma-separated weights (default: the file's, else equal)")
        func = _blend
    else:
        p.description = ("Sample the motion through the keyframes in FILE (on the server at "
                         "--server, or --local). Times outside the keyframe range are an error: "
                         "the motion is never extrapolated.")
        p.epilog = (POSE_FORMATS % (INTERPOLATE_JSON, "keyframes", INTERPOLATE_CSV)
                    + "\nexample: dqpose interpolate --step 0.002 --mode tool_linear keyframes.csv")
        p.add_argument("file", metavar="FILE",
                       help="keyframes (JSON, YAML or CSV; - reads standard input)")
        p.add_argument("--mode", choices=["screw", "tool_linear"],
                       help="screw: piecewise ScLERP; tool_linear: straight tool path, slerped "
                            "orientation (default: the file's \"interpolation\", else screw)")
        g = p.add_mutually_exclusive_group()
        g.add_argument("--times", help="comma-separated sample times, s (default: the file's "
                                       "\"times\", else every --step)")
        g.add_argument("--step", type=float,
                       help="sample period over the whole keyframe range, s "
                            "(default 0.01); the last keyframe time is included")
        func = _interpolate
    p.add_argument("--format", choices=["auto", "csv", "json"], default="auto",
                   help="output format; auto = the input's (default: %(default)s)")
    p.add_argument("--local", action="store_true", help="compute in this process, no server")
    add_quaternion_order(p)
    connection_args(p)
    p.set_defaults(func=func)


def _blend(args) -> int:
    from dqpose import dq
    from dqpose.cli import posefile as io

    try:
        req = io.read_blend(args.file, args.quaternion_order)
        method = args.method or req.method or "dib"
        weights = io.parse_floats("--weights", args.weights) if args.weights else req.weights
        fmt = req.format if args.format == "auto" else args.format
        if args.local:
            info = dq.dib(req.dqs, weights, return_info=True) if method == "dib" else None
            mean = info.mean if info else dq.blend(req.dqs, weights, method)
            iterations, residual = ((int(info.iterations), float(info.residual)) if info
                                    else (0, 0.0))
        else:
            with client(args) as c:
                mean, iterations, residual = c.blend(req.dqs, weights, method, return_info=True)
    except Exception as e:
        return failure("blend", args, e)
    sys.stdout.write(io.format_blend(mean, iterations, residual, fmt))
    return 0


def _interpolate(args) -> int:
    from dqpose.cli import posefile as io
    from dqpose.interpolate import interpolate

    try:
        req = io.read_interpolate(args.file, args.quaternion_order)
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
            with client(args) as c:
                out = c.interpolate(req.times_k, req.dqs_k, times, mode)
    except Exception as e:
        return failure("interpolate", args, e)
    sys.stdout.write(io.format_samples(times, out, fmt))
    return 0
