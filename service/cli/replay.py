"""``dqpose replay FILE.mcap|DIR ...``: a recording's calls fed again (in this process or to a
server), every answer compared with the recorded one byte for byte; a server's rotated files (a
directory, several files, a glob) are replayed as one sequence, run by run. ``--compare OTHER``
compares two recordings of the same requests instead. Exit 0 when every answer is the same, 1 at
the first difference (printed), 2 when not every answer could be compared (a file cut short or
damaged, messages the recorder dropped: what precedes is replayed, and where and why each run
stopped is printed), for a file that is not a recording, or a missing extra."""
from __future__ import annotations

import argparse
import sys

from dqpose.cli.common import fail, missing_extra, read


def configure(name: str, p) -> None:
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.description = __doc__.split("\n\n")[0].replace("``", "")
    p.add_argument("file", metavar="FILE.mcap", nargs="+",
                   help="a recording (dqpose serve --record): files, the directory they are "
                        "in, or a glob; a server's rotated files replay as one sequence")
    p.add_argument("--speed", default="max",
                   help="'max' (default): each request as soon as the last is answered; a "
                        "number: that many times the recorded pace (1: as recorded)")
    p.add_argument("--server", metavar="HOST:PORT",
                   help="feed a server there (default: this process's servicers, with the "
                        "server's default limits)")
    p.add_argument("--token-file", help="file holding the server's bearer token")
    p.add_argument("--compare", metavar="OTHER",
                   help="compare FILE's answers with OTHER's (a file, directory or glob: the "
                        "same requests recorded by another version or setting), run by run, "
                        "instead of replaying")
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
        from dqpose.record.reader import runs as runs_of
        from dqpose.rpc import replay
    except (MissingExtra, ModuleNotFoundError) as e:
        return missing_extra("replay", e)
    try:
        speed = _speed(args.speed)
        runs = runs_of(args.file)
        other = runs_of([args.compare]) if args.compare else None
        if other is not None:
            report = replay.compare_runs(runs, other)
            verb = "compared"
        else:
            if args.server:
                import grpc
                token = read(args.token_file, "r").strip() if args.token_file else None
                metadata = (("authorization", f"Bearer {token}"),) if token else None
                target = replay.Remote(grpc.insecure_channel(args.server), metadata)
            else:
                target = replay.InProcess()
            report = replay.replay(runs, target, speed)
            verb = "replayed"
    except (OSError, ValueError) as e:
        return fail("replay", str(e) if not isinstance(e, OSError) or not e.filename
                    else f"{e.filename}: {e.strerror}")
    for line in report.skipped:
        print(f"skipped {line}", file=sys.stderr)
    rate = f" in {report.seconds:.3f} s" if other is None else ""
    files = (f" from {report.files} files in {report.runs} run"
             f"{'s' if report.runs != 1 else ''}" if report.files > 1 else "")
    print(f"{verb} {report.calls} calls, {report.requests} requests, {report.answers} "
          f"answers{files}{rate}")
    for cut in report.cuts:
        print(cut)
    if report.difference is not None:
        print(f"first difference: {report.difference}")
        return 1
    if report.cuts:
        where = "it" if len(report.cuts) == 1 else "each run"
        print(f"no difference up to where {where} stopped; what follows was not {verb}"
              if report.calls else f"nothing {verb}")
        return 2
    print("every answer identical" if report.calls else "nothing to compare")
    return 0
