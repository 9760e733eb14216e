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
    p.add_argument("file", metavar="FILE.mcap", nargs="?",
                   help="a recording (dqpose serve --record)")
    p.add_argument("--server", metavar="HOST:PORT",
                   help="follow a server live instead: the address of its `serve --live` "
                        "WebSocket (the [view] extra's websockets client)")
    p.add_argument("--host", default="127.0.0.1",
                   help="the page's address (default: %(default)s; 0.0.0.0 for other machines)")
    p.add_argument("--port", type=int, default=8080,
                   help="the page's port; the next free one when taken (default: %(default)s)")
    p.set_defaults(func=_view)


def _view(args) -> int:
    from dqpose.errors import MissingExtra, require
    from dqpose.view import MODULES

    if (args.file is None) == (args.server is None):
        return fail("view", "give a recording FILE.mcap or --server HOST:PORT (one of them)")
    try:
        require(*MODULES, *(("websockets",) if args.server else ()))
        from dqpose.record.reader import read
        from dqpose.view.page import Page, Scene
        from dqpose.view.timeline import timeline
    except (MissingExtra, ModuleNotFoundError) as e:
        return missing_extra("view", e)
    if not 0 <= args.port <= 65535:
        return fail("view", f"--port: must be within 0..65535, got {args.port}")
    if args.server is not None:
        return _follow(args, Scene)
    try:
        tl = timeline(read(args.file))
    except OSError as e:
        return fail("view", f"{e.filename or args.file}: {e.strerror or e}")
    except ValueError as e:
        return fail("view", str(e))
    page = Page(tl, host=args.host, port=args.port)
    print(json.dumps({"event": "viewing", "url": f"http://{args.host}:{page.port}",
                      "bodies": sorted(tl.tracks), "plans": page.plan_names,
                      "arms": sorted(tl.arms),
                      "seconds": (tl.end - tl.start) * 1e-9}), file=sys.stderr, flush=True)
    done = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: done.set())
    done.wait()
    page.close()
    return 0


def _follow(args, Scene) -> int:
    from dqpose.record import parse_address
    from dqpose.view.follow import Follower

    try:
        host, port = parse_address(args.server)
    except ValueError as e:
        return fail("view", str(e).replace("--live", "--server"))
    scene = Scene(host=args.host, port=args.port)
    follower = Follower(f"ws://{host}:{port}", scene)
    done = threading.Event()
    why: list[str] = []

    def follow() -> None:
        try:
            follower.run()
            why.append(f"--server {host}:{port}: the server closed the connection")
        except Exception as e:      # refused, reset, a handshake refused: said, then exit 1
            why.append(f"--server {host}:{port}: {e}")
        done.set()

    print(json.dumps({"event": "viewing", "url": f"http://{args.host}:{scene.port}",
                      "server": f"ws://{host}:{port}"}), file=sys.stderr, flush=True)
    threading.Thread(target=follow, name="dqpose-view-follow", daemon=True).start()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: done.set())
    done.wait()
    scene.close()
    return fail("view", why[0]) if why else 0
