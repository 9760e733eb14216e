"""``dqpose view FILE.mcap``: a recording on a local web page (viser, the ``[view]`` extra): the
bodies' frames where they were fused, their position's 3-sigma ellipsoids, the plans, and a time
slider over the file. Serves until Ctrl-C; says where on standard error (JSON: ``viewing``, its
``url``, the bodies and plans)."""
from __future__ import annotations

import json
import signal
import sys
import threading

from dqpose.cli.common import fail, missing_extra


def configure(name: str, p) -> None:
    p.description = __doc__.split("\n\n")[0].replace("``", "")
    p.add_argument("file", metavar="FILE.mcap", help="a recording (dqpose serve --record)")
    p.add_argument("--host", default="127.0.0.1",
                   help="the page's address (default: %(default)s; 0.0.0.0 for other machines)")
    p.add_argument("--port", type=int, default=8080,
                   help="the page's port; the next free one when taken (default: %(default)s)")
    p.set_defaults(func=_view)


def _view(args) -> int:
    from dqpose.errors import MissingExtra, require
    from dqpose.view import MODULES

    try:
        require(*MODULES)
        from dqpose.record.reader import read
        from dqpose.view.page import Page
        from dqpose.view.timeline import timeline
    except (MissingExtra, ModuleNotFoundError) as e:
        return missing_extra("view", e)
    if not 0 <= args.port <= 65535:
        return fail("view", f"--port: must be within 0..65535, got {args.port}")
    try:
        tl = timeline(read(args.file))
    except OSError as e:
        return fail("view", f"{e.filename or args.file}: {e.strerror or e}")
    except ValueError as e:
        return fail("view", str(e))
    page = Page(tl, host=args.host, port=args.port)
    print(json.dumps({"event": "viewing", "url": f"http://{args.host}:{page.port}",
                      "bodies": sorted(tl.tracks), "plans": page.plan_names,
                      "seconds": (tl.end - tl.start) * 1e-9}), file=sys.stderr, flush=True)
    done = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: done.set())
    done.wait()
    page.close()
    return 0
