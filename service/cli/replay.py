"""``dqpose replay FILE.mcap``: a recording's calls fed again (in this process or to a server),
every answer compared with the recorded one byte for byte; ``--compare OTHER.mcap`` compares two
recordings of the same requests instead. Exit 0 when every answer is the same, 1 at the first
difference (printed), 2 for a file that cannot be read or a missing extra."""
from __future__ import annotations

import argparse
import sys

from dqpose.cli.common import fail, missing_extra, read


def configure(name: str, p) -> None:
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.description = __doc__.split("\n\n")[0].replace("``", "")
    p.add_argument("file", metavar="FILE.mcap", help="a recording (dqpose serve --record)")
    p.add_argument("--speed", default="max",
                   help="'max' (default): each request as soon as the last is answered; a "
                        "number: that many times the recorded pace (1: as recorded)")
    p.add_argument("--server", metavar="HOST:PORT",
                   help="feed a server there (default: this process's servicers, with the "
                        "server's default limits)")
    p.add_argument("--token-file", help="file holding the server's bearer token")
    p.add_argument("--compare", metavar="OTHER.mcap",
                   help="compare FILE's answers with OTHER's (the same requests recorded by "
                        "another version or setting) instead of replaying")
    p.set_defaults(func=_replay)


def _speed(text: str):
    if text == "max":
        return None
    try:
        speed = float(text)
    except ValueError:
        speed = 0.0
    if not speed > 0 or speed == float("inf"):
        raise ValueError(f"--speed: 'max' or a number > 0, got {text!r}")
    return speed


def _replay(args) -> int:
    from dqpose.errors import MissingExtra
    from dqpose.record import MODULES

    try:
        from dqpose.errors import require
        require(*MODULES)
        from dqpose.record.reader import read as read_recording
        from dqpose.rpc import replay
    except (MissingExtra, ModuleNotFoundError) as e:
        return missing_extra("replay", e)
    try:
        speed = _speed(args.speed)
        rec = read_recording(args.file)
        other = read_recording(args.compare) if args.compare else None
    except (OSError, ValueError) as e:
        return fail("replay", str(e) if not isinstance(e, OSError) or not e.filename
                    else f"{e.filename}: {e.strerror}")
    if other is not None:
        report = replay.compare(rec, other)
        verb = "compared"
    else:
        if args.server:
            import grpc
            token = read(args.token_file, "r").strip() if args.token_file else None
            metadata = (("authorization", f"Bearer {token}"),) if token else None
            target = replay.Remote(grpc.insecure_channel(args.server), metadata)
        else:
            target = replay.InProcess()
        report = replay.replay(rec, target, speed)
        verb = "replayed"
    for line in report.skipped:
        print(f"skipped {line}", file=sys.stderr)
    rate = f" in {report.seconds:.3f} s" if other is None else ""
    print(f"{verb} {report.calls} calls, {report.requests} requests, {report.answers} "
          f"answers{rate}")
    if report.cut:
        print(report.cut)
    if report.difference is not None:
        print(f"first difference: {report.difference}")
        return 1
    print("every answer identical" if report.calls else "nothing to compare")
    return 0
