"""``dqpose fuse``: measurements of one body from a JSON, YAML or CSV file, fused on a server (the
``dqpose.v1.Fusion`` service) or ``--local``ly by :func:`dqpose.fusion.fuse` with the server's
checks of the request (no grpc imported), printed as text or JSON."""
from __future__ import annotations

import argparse
import sys

from dqpose.cli.common import client, connection_args, failure
from dqpose.cli.inputs import add_quaternion_order

AXES = ("wx", "wy", "wz", "vx", "vy", "vz")
BASE_COLUMNS = ("source", "time", "x", "y", "z", "qw", "qx", "qy", "qz")
SIGMA_COLUMNS = tuple(f"sigma_{a}" for a in AXES)
COVARIANCE_COLUMNS = tuple(f"c{i}{j}" for i in range(6) for j in range(6))
NUMBER_COLUMNS = ("weight",) + SIGMA_COLUMNS + COVARIANCE_COLUMNS    # optional, by header

EPILOG = """\
input formats (FILE, or - for standard input; chosen by the extension, else sniffed):
  JSON  the FuseRequest body grpcurl sends to dqpose.v1.Fusion/Fuse, e.g.
          {"measurements": [
             {"source": "cam1", "body": "box", "time": 12.5,
              "pose": {"position": {"x": 0.5, "y": 0, "z": 0.3},
                       "orientation": {"w": 1, "x": 0, "y": 0, "z": 0}},
              "covariance": [36 values, row-major]},
             {"source": "arm", "pose": {...}, "weight": 4}, ...],
           "options": {"robust": true, "max_skew": 0.1,
                       "sources": [{"name": "cam1", "latency": 0.04,
                                    "extrinsic": {"position": {...}, "orientation": {...}}},
                                   {"name": "arm", "latency": 0.004, "latency_sigma": 0.005,
                                    "body_offset": {...}}]}}
        a bare list of measurements is accepted too. An orientation may also be given as
        "orientation_xyzw": [x, y, z, w] or "orientation_wxyz": [w, x, y, z], a position as
        [x, y, z].
  CSV   one measurement per line, columns source,time,x,y,z,qw,qx,qy,qz (matched by the
        header's names, any order; a file without a header needs --quaternion-order) and
        optionally:
          body                      the body (all lines name the same one)
          sigma_wx .. sigma_vz      standard deviations of [wx wy wz vx vy vz] (rad, m):
                                    a diagonal covariance
          c00 c01 .. c55            the full covariance, row i column j
          weight                    isotropic covariance I / weight
        neither: identity covariance. A header line is needed for the optional columns.
        (frames of the sources: use JSON's "options".)
covariance convention: 6x6, rotation first [wx wy wz vx vy vz] (radians, then metres), for a
right (body-frame) perturbation: the true pose is T * Exp(xi), xi ~ N(0, Sigma) (GTSAM's Pose3).
A measurement is T_frame_body in its source's frame; the fused pose is T_world_body.

time: a measurement stamped t by a source with latency L was taken at t - L. Measurements taken
at different instants are fused at the fusion time (--time; default the newest instant) under a
constant body twist estimated with the pose; all taken at one instant, they give the static
fusion exactly.

output: the fused pose, its covariance, chi2 and dof, the measurements the robust mode rejected
and those dropped for --max-skew with the reason, the body twist and the latencies estimated
online (with time alignment), and per source its mean normalised innovation squared (NIS, 6
expected) and verdict (consistent, optimistic: claims too small a covariance, pessimistic,
untested).

example: dqpose fuse --robust --local measurements.csv
"""


def configure(name: str, p) -> None:
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.description = ("Fuse the measurements of one body in FILE into its maximum-likelihood pose "
                     "with a covariance (on the server at --server, or --local).")
    p.epilog = EPILOG
    p.add_argument("file", metavar="FILE",
                   help="measurements (JSON, YAML or CSV; - reads standard input)")
    p.add_argument("--robust", action="store_true",
                   help="reject gross outliers (default: the file's \"options\", else off)")
    p.add_argument("--probability", type=float,
                   help="of the outlier gate and the consistency intervals (default: the "
                        "file's, else 0.999)")
    p.add_argument("--time", type=float,
                   help="fusion time, s (default: the file's, else the newest measurement's)")
    p.add_argument("--max-skew", type=float,
                   help="drop measurements taken further than this from the fusion time, s "
                        "(default: the file's, else none dropped)")
    p.add_argument("--max-extrapolation", type=float,
                   help="how far the fusion time may lie outside the measurements' span, s; "
                        "inf: unbounded (default: the file's, else 0.1)")
    p.add_argument("--acceleration-psd", type=float, nargs=2, metavar=("ROT", "TRANS"),
                   help="let the twist drift: white-noise acceleration with this power spectral "
                        "density on each rotation (rad^2/s^3) and translation (m^2/s^3) axis; "
                        "rule of thumb a^2 * window (default: the file's, else a constant twist)")
    p.add_argument("--format", choices=["text", "json"], default="text",
                   help="output: text for people, or the FusedPose as JSON (default: %(default)s)")
    p.add_argument("--local", action="store_true", help="compute in this process, no server")
    add_quaternion_order(p)
    connection_args(p)
    p.set_defaults(func=_fuse)


def read_request(path: str, order: str | None = None):
    """A ``FuseRequest`` from a JSON, YAML or CSV file (see the help); ``order``
    (``--quaternion-order``) of quaternions not named one by one."""
    from dqpose.cli import inputs
    from dqpose.rpc._proto.dqpose.v1 import fusion_pb2 as pb

    text, fmt = inputs.load(path)
    if fmt != "csv":
        from google.protobuf import json_format

        doc = inputs.document(path, text, fmt, "measurements")
        inputs.message("", doc, pb.FuseRequest.DESCRIPTOR, order)
        try:
            request = json_format.ParseDict(doc, pb.FuseRequest())
        except json_format.ParseError as e:
            raise ValueError(f"{path}: not a dqpose.v1.FuseRequest: {e}") from None
    else:
        request = pb.FuseRequest(measurements=_csv_measurements(text, order))
    if not request.measurements:
        raise ValueError(f"{path}: no measurements")
    return request


def _csv_measurements(text: str, order: str | None) -> list:
    from dqpose.cli import inputs, posefile
    from dqpose.rpc._proto.dqpose.v1 import fusion_pb2 as pb

    # The text columns (source, body) are taken out, the numbers read by posefile's reader.
    lines = [cells for _, cells in inputs.table(text)]
    if not lines:
        return []
    header = None if any(inputs.is_number(c) for c in lines[0]) else [
        c.strip().lower() for c in lines[0]]
    cols = header or list(BASE_COLUMNS)
    texts = {c: cols.index(c) for c in ("source", "body") if c in cols}
    numbers = [i for i, c in enumerate(cols) if c not in texts]
    body_rows = lines[1:] if header else lines
    table = "\n".join(",".join(r[i] if i < len(r) else "" for i in numbers) for r in
                      ([header] if header else []) + body_rows)
    if "source" not in texts:
        raise ValueError(f"line 1: missing column source; expected {','.join(BASE_COLUMNS)}")
    unknown = [c for c in cols if c not in BASE_COLUMNS + ("body",) + NUMBER_COLUMNS]
    if unknown:
        raise ValueError(f"line 1: unknown column {unknown[0]!r}; expected "
                         f"{','.join(BASE_COLUMNS)} and optionally body, weight, "
                         f"sigma_wx..sigma_vz or c00..c55 (see --help)")
    rows = posefile.csv_rows(table, BASE_COLUMNS[1:], NUMBER_COLUMNS, order=order,
                              taken=("source",))
    have = [c for c in NUMBER_COLUMNS if c in cols]
    groups = {"weight": [c for c in have if c == "weight"],
              "sigma": [c for c in have if c in SIGMA_COLUMNS],
              "covariance": [c for c in have if c in COVARIANCE_COLUMNS]}
    for name, want in (("sigma", SIGMA_COLUMNS), ("covariance", COVARIANCE_COLUMNS)):
        if groups[name] and len(groups[name]) != len(want):
            missing = next(c for c in want if c not in groups[name])
            raise ValueError(f"line 1: missing column {missing} (the {name} columns come all "
                             f"together)")
    given = [g for g in ("weight", "sigma", "covariance") if groups[g] and groups[g][0] in have]
    if len(given) > 1:
        raise ValueError(f"line 1: columns of both {given[0]} and {given[1]}; give one")
    at = {c: 8 + k for k, c in enumerate(have)}
    out = []
    for line, r in zip(body_rows, rows):
        m = pb.Measurement(source=line[texts["source"]].strip(), time=r[0],
                           body=line[texts["body"]].strip() if "body" in texts else "")
        m.pose.position.x, m.pose.position.y, m.pose.position.z = r[1:4]
        o = m.pose.orientation
        o.w, o.x, o.y, o.z = r[4:8]
        if "weight" in given:
            m.weight = r[at["weight"]]
        elif "sigma" in given:
            sd = [r[at[c]] for c in SIGMA_COLUMNS]
            m.covariance.extend(sd[i] * sd[i] if i == j else 0.0
                                for i in range(6) for j in range(6))
        elif "covariance" in given:
            m.covariance.extend(r[at[c]] for c in COVARIANCE_COLUMNS)
        out.append(m)
    return out


def _fuse(args) -> int:
    try:
        request = read_request(args.file, args.quaternion_order)
        if args.robust:
            request.options.robust = True
        if args.probability is not None:
            request.options.probability = args.probability
        if args.time is not None:
            request.options.time = args.time
        if args.max_skew is not None:
            request.options.max_skew = args.max_skew
        if args.max_extrapolation is not None:
            request.options.max_extrapolation = args.max_extrapolation
        if args.acceleration_psd is not None:
            rot, trans = args.acceleration_psd
            del request.options.acceleration_psd[:]
            request.options.acceleration_psd.extend(
                (rot if i < 3 else trans) if i == j else 0.0 for i in range(6) for j in range(6))
        if args.local:
            # dqpose.fusion.fuse with the checks and field names of the server's Fuse
            from dqpose.rpc.fusion_convert import fused_pose

            fused = fused_pose(request)
        else:
            with client(args) as c:
                fused = c.fuse_request(request)
    except Exception as e:
        return failure("fuse", args, e)
    sys.stdout.write(format_fused(fused, args.format))
    return 0


def format_fused(msg, fmt: str) -> str:
    """A ``FusedPose`` as text for people, or as its JSON (proto field names)."""
    from google.protobuf import json_format

    if fmt == "json":
        return json_format.MessageToJson(msg, preserving_proto_field_name=True) + "\n"
    from dqpose.rpc._proto.dqpose.v1 import fusion_pb2 as pb

    p, o = msg.pose.position, msg.pose.orientation
    sign = -1.0 if o.w < 0 else 1.0          # q and -q are one rotation; print w >= 0
    lines = [f"body {msg.body!r} at time {msg.time:.9g} s: "
             f"{pb.FusionStatus.Name(msg.status)[len('FUSION_STATUS_'):].lower()} in "
             f"{msg.iterations} iterations",
             "pose T_world_body (x,y,z,qw,qx,qy,qz):",
             "  " + ",".join(f"{v:.12g}" for v in (p.x, p.y, p.z, sign * o.w, sign * o.x,
                                                   sign * o.y, sign * o.z)),
             "covariance (rotation first [wx wy wz vx vy vz], right perturbation):"]
    c = list(msg.covariance)
    lines += ["  " + " ".join(f"{v: .6e}" for v in c[6 * i:6 * i + 6]) for i in range(6)]
    lines.append(f"chi2 {msg.chi2:.6g} with {msg.dof} dof; inliers "
                 f"{','.join(str(i) for i in msg.inliers)}")
    if msg.rejected:
        lines.append("rejected:")
        lines += [f"  {reason}" for reason in msg.reasons]
    if msg.dropped:
        lines.append("dropped:")
        lines += [f"  {d.reason}" for d in msg.dropped]
    if msg.twist:
        lines.append("body twist V (wx,wy,wz rad/s, vx,vy,vz m/s; T(t) = pose * Exp((t - time) V)) "
                     "and its standard deviations:")
        sd = [max(c, 0.0) ** 0.5 for c in list(msg.twist_covariance)[::7]]
        lines.append("  " + ",".join(f"{v:.6g}" for v in msg.twist))
        lines.append("  " + ",".join(f"{v:.3g}" for v in sd))
    if msg.extrapolation:
        lines.append(f"extrapolated {msg.extrapolation:.6g} s beyond the measurements")
    for a in msg.latencies:
        lines.append(f"latency of {a.source}: {a.value:.6g} +- {a.sigma:.3g} s "
                     f"(configured {a.configured:g} +- {a.prior_sigma:g} s)")
    lines.append("sources (NIS: normalised innovation squared, 6 expected):")
    for s in msg.sources:
        verdict = pb.Verdict.Name(s.verdict)[len("VERDICT_"):].lower()
        lines.append(f"  {s.name or '(unnamed)'}: {s.count} tested, {s.rejected} rejected, "
                     f"NIS mean {s.nis_mean:.4g} in [{s.low:.4g}, {s.high:.4g}]: {verdict}"
                     if s.count else
                     f"  {s.name or '(unnamed)'}: {s.rejected} rejected, {verdict}")
    return "\n".join(lines) + "\n"
