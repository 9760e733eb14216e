"""``dqpose view FILE.mcap``: a recording on a local web page (viser, the ``[view]`` extra): the
bodies' frames where they were fused, their position's 3-sigma ellipsoids, the plans, the arms'
actual paths, and a time slider over the file. ``--server HOST:PORT`` follows a server live
instead (its World's bodies through Subscribe, its arms through WatchArm), ``--live HOST:PORT``
a ``serve --live`` WebSocket. Serves until Ctrl-C; says where on standard error (JSON:
``viewing``, its ``url``, the bodies, plans and arms)."""
from __future__ import annotations

import json
import signal
import sys
import threading
import urllib.parse

from dqpose.cli.common import fail, missing_extra


def configure(name: str, p) -> None:
    p.description = __doc__.split("\n\n")[0].replace("``", "")
    p.add_argument("file", metavar="FILE.mcap", nargs="?",
                   help="a recording (dqpose serve --record)")
    live = p.add_mutually_exclusive_group()
    live.add_argument("--server", metavar="HOST:PORT",
                      help="follow a dqpose server live instead (its gRPC address): the "
                           "World's bodies as they are fused, its arms as they move")
    live.add_argument("--live", metavar="HOST:PORT",
                      help="follow a `serve --live` WebSocket instead (the [view] extra's "
                           "websockets client)")
    p.add_argument("--token-file", help="with --server or --live: file holding the server's "
                                        "bearer token")
    p.add_argument("--host", default="127.0.0.1",
                   help="the page's address (default: %(default)s; 0.0.0.0 for other machines)")
    p.add_argument("--port", type=int, default=8080,
                   help="the page's port; the next free one when taken (default: %(default)s)")
    p.set_defaults(func=_view)


def _view(args) -> int:
    from dqpose.errors import MissingExtra, require
    from dqpose.view import MODULES

    following = args.server or args.live
    if (args.file is None) == (following is None):
        return fail("view", "give a recording FILE.mcap, --server HOST:PORT or --live "
                            "HOST:PORT (one of them)")
    try:
        require(*MODULES, *(("websockets",) if args.live else ()))
        from dqpose.record.reader import read
        from dqpose.view.page import Page, Scene
        from dqpose.view.timeline import timeline
    except (MissingExtra, ModuleNotFoundError) as e:
        return missing_extra("view", e)
    if not 0 <= args.port <= 65535:
        return fail("view", f"--port: must be within 0..65535, got {args.port}")
    if args.server is not None:
        return _watch(args, Scene)
    if args.live is not None:
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
    _serve_until_done(threading.Event())
    page.close()
    return 0


def _serve_until_done(done: threading.Event) -> None:
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: done.set())
    done.wait()


def _watch(args, Scene) -> int:
    from dqpose.cli.common import read
    from dqpose.rpc.client import RpcError
    from dqpose.view.watch import Watcher

    token = read(args.token_file, "r").strip() if args.token_file else None
    scene = Scene(host=args.host, port=args.port)
    watcher = Watcher(args.server, scene, token=token)
    print(json.dumps({"event": "viewing", "url": f"http://{args.host}:{scene.port}",
                      "server": args.server}), file=sys.stderr, flush=True)
    try:
        watcher.start()
    except RpcError as e:
        watcher.why = f"--server {args.server}: {e}"
        watcher.failed.set()
    done = threading.Event()
    threading.Thread(target=lambda: (watcher.failed.wait(), done.set()), daemon=True).start()
    _serve_until_done(done)
    scene.close()
    watcher.close()
    return fail("view", watcher.why) if watcher.failed.is_set() else 0


def _follow(args, Scene) -> int:
    from dqpose.cli.common import read
    from dqpose.record import parse_address
    from dqpose.view.follow import Follower

    try:
        host, port = parse_address(args.live)
    except ValueError as e:
        return fail("view", str(e))
    token = read(args.token_file, "r").strip() if args.token_file else None
    query = "" if token is None else "/?" + urllib.parse.urlencode({"token": token})
    scene = Scene(host=args.host, port=args.port)
    follower = Follower(f"ws://{host}:{port}{query}", scene)
    done = threading.Event()
    why: list[str] = []

    def follow() -> None:
        try:
            follower.run()
            why.append(f"--live {host}:{port}: the server closed the connection")
        except Exception as e:      # refused, reset, a handshake refused: said, then exit 1
            why.append(f"--live {host}:{port}: {e}")
        done.set()

    print(json.dumps({"event": "viewing", "url": f"http://{args.host}:{scene.port}",
                      "server": f"ws://{host}:{port}"}), file=sys.stderr, flush=True)
    threading.Thread(target=follow, name="dqpose-view-follow", daemon=True).start()
    _serve_until_done(done)
    scene.close()
    return fail("view", why[0]) if why else 0
