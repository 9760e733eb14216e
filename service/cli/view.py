"""``dqpose view FILE.mcap``: a recording on a local web page (viser, the ``[view]`` extra): the
bodies' frames where they were fused, their position's 3-sigma ellipsoids, the plans, the arms'
actual paths, and a time slider over the file. ``--server HOST:PORT`` follows a server live
instead (its World's bodies through Subscribe, its arms through WatchArm), ``--live HOST:PORT``
a ``serve --live`` WebSocket. Serves until Ctrl-C; says where on standard error (JSON:
``viewing``, its ``url``, the bodies, plans and arms)."""
from __future__ import annotations

import os
import signal
import sys
import threading

from dqpose.cli.common import fail, missing_extra, read
from dqpose.events import say_err


def configure(name: str, p) -> None:
    p.description = __doc__.split("\n\n")[0].replace("``", "")
    p.add_argument("file", metavar="FILE.mcap", nargs="?",
                   help="a recording (dqpose serve --record): a file, the directory it is in "
                        "or a glob, as replay takes them; a server's rotated files show as "
                        "one, the newest run of several")
    live = p.add_mutually_exclusive_group()
    live.add_argument("--server", metavar="HOST:PORT",
                      help="follow a dqpose server live instead (its gRPC address): the "
                           "World's bodies as they are fused, its arms as they move")
    live.add_argument("--live", metavar="HOST:PORT",
                      help="follow a `serve --live` WebSocket instead (the [view] extra's "
                           "websockets client)")
    p.add_argument("--token-file", help="with --server or --live: file holding the server's "
                                        "bearer token (the page then serves the loopback only)")
    p.add_argument("--host", default="127.0.0.1",
                   help="the page's address (default: %(default)s; 0.0.0.0 for other machines: "
                        "the page has no password)")
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
        from dqpose.record.reader import read_all
        from dqpose.record.reader import runs as runs_of
        from dqpose.view.page import Page, Scene
        from dqpose.view.timeline import timeline
    except (MissingExtra, ModuleNotFoundError) as e:
        return missing_extra("view", e)
    if not 0 <= args.port <= 65535:
        return fail("view", f"--port: must be within 0..65535, got {args.port}")
    if following is not None:
        try:
            token = _token(args)
        except ValueError as e:
            return fail("view", str(e))
        return (_watch if args.server else _follow)(args, Scene, token)
    if args.token_file:
        return fail("view", "--token-file: only with --server or --live (a file needs none)")
    try:
        runs = runs_of([args.file])
        tl = timeline(read_all(runs[-1]))
    except OSError as e:
        return fail("view", f"{e.filename or args.file}: {e.strerror or e}")
    except ValueError as e:
        return fail("view", str(e))
    if len(runs) > 1:
        print(f"dqpose view: {args.file} holds {len(runs)} runs; showing the last by name "
              f"({os.path.basename(runs[-1][0])}, {len(runs[-1])} file"
              f"{'s' if len(runs[-1]) > 1 else ''}); name a file to see another",
              file=sys.stderr)
    page = Page(tl, host=args.host, port=args.port)
    say_err(event="viewing", url=f"http://{args.host}:{page.port}", files=runs[-1],
            bodies=sorted(tl.tracks), plans=page.plan_names, arms=sorted(tl.arms),
            seconds=(tl.end - tl.start) * 1e-9)
    _serve_until_done(threading.Event())
    page.close()
    return 0


def _token(args) -> str | None:
    """The token of ``--token-file`` (none: ``None``); ``ValueError`` saying why not, or why
    not with this ``--host``."""
    from dqpose.view.guard import LOOPBACK

    if not args.token_file:
        return None
    try:
        token = read(args.token_file, "r").strip()
    except OSError as e:
        raise ValueError(f"--token-file {args.token_file}: {e.strerror or e}") from None
    if not token:
        raise ValueError(f"--token-file {args.token_file}: empty")
    if args.host not in LOOPBACK:
        # what a token protects would be served to anyone reaching --host
        port = args.port or 8080
        raise ValueError(f"--host {args.host}: the page has no authentication, so with "
                         f"--token-file it serves the loopback only (from another machine: "
                         f"ssh -L {port}:127.0.0.1:{port} this one)")
    return token


def _serve_until_done(done: threading.Event) -> None:
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: done.set())
    done.wait()


def _watch(args, Scene, token: str | None) -> int:
    from dqpose.rpc.client import RpcError
    from dqpose.view.watch import Watcher

    scene = Scene(host=args.host, port=args.port)
    watcher = Watcher(args.server, scene, token=token)
    say_err(event="viewing", url=f"http://{args.host}:{scene.port}", server=args.server)
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


def _follow(args, Scene, token: str | None) -> int:
    from urllib.parse import urlencode

    from dqpose.record import parse_address
    from dqpose.view.follow import Follower

    try:
        host, port = parse_address(args.live)
    except ValueError as e:
        return fail("view", str(e))
    scene = Scene(host=args.host, port=args.port)
    # serve --live takes a token as a query parameter (a browser's WebSocket sends no header)
    follower = Follower(f"ws://{host}:{port}" + (f"/?{urlencode({'token': token})}"
                                                  if token else ""), scene)
    done = threading.Event()
    why: list[str] = []

    def follow() -> None:
        try:
            follower.run()
            why.append(f"--live {host}:{port}: the server closed the connection")
        except Exception as e:      # refused, reset, a handshake refused: said, then exit 1
            why.append(f"--live {host}:{port}: {e}")
        done.set()

    say_err(event="viewing", url=f"http://{args.host}:{scene.port}", server=f"ws://{host}:{port}")
    threading.Thread(target=follow, name="dqpose-view-follow", daemon=True).start()
    _serve_until_done(done)
    scene.close()
    return fail("view", why[0]) if why else 0
