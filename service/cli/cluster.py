"""``dqpose cluster`` (``make cluster``): scale-out tried on one machine, without Docker: N
``dqpose serve`` replicas on free loopback ports and HAProxy (or nginx) in front of them, running
the shipped configuration (docker/haproxy.cfg, docker/nginx.conf) with its server lines rewritten
to the replicas and its front end bound to ``--host``:``--port``; until Ctrl-C or SIGTERM.

What the rewriting keeps is the shipped file's every other line (hashing on ``x-dqpose-world``,
health checks, timeouts), so the loopback cluster behaves as the compose one: tests/cluster/ runs
the proxies through :class:`Proxy` and :class:`Replica` too.
"""
from __future__ import annotations

import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time

from dqpose.events import say_err

#: each proxy: its executable, the Debian package that has it, the shipped configuration
PROXIES = {"haproxy": ("haproxy", "haproxy", "haproxy.cfg"),
           "nginx": ("nginx", "nginx-light", "nginx.conf")}
#: a replica's address in the shipped configurations (compose's service name and port)
COMPOSE_ADDRESS = re.compile(r"dqpose-\d+:50051")
#: the front end's line in each shipped configuration, and how it is written for an address
FRONT_END = {"haproxy": (r"bind :50051\b", "bind {}"), "nginx": (r"listen 50051\b", "listen {}")}


def missing(proxy: str) -> str | None:
    """Why ``proxy`` cannot run here (the package to install), or None."""
    exe, package, _ = PROXIES[proxy]
    if shutil.which(exe) or os.path.exists(f"/usr/sbin/{exe}"):
        return None
    return f"{exe} is not installed (apt-get install -y {package})"


def executable(proxy: str) -> str:
    exe = PROXIES[proxy][0]
    return shutil.which(exe) or f"/usr/sbin/{exe}"


def proxy_config(kind: str, text: str, replicas: list[tuple[str, str]], listen: str) -> str:
    """The shipped configuration ``text`` of ``kind`` ("haproxy" or "nginx") in front of
    ``replicas`` (``(name, host:port)`` each, any number): each run of server lines naming the
    compose replicas (``dqpose-N:50051``) becomes one line per replica, written as the run's first
    line is, with its address and (HAProxy's server name) its name; the front end on ``listen``
    (``host:port``). ValueError when the text has no such server lines or front end."""
    if not replicas:
        raise ValueError("replicas: at least one")
    out: list[str] = []
    runs = 0
    lines = text.splitlines(True)
    for i, line in enumerate(lines):
        if not COMPOSE_ADDRESS.search(line):
            out.append(line)
            continue
        if i > 0 and COMPOSE_ADDRESS.search(lines[i - 1]):
            continue            # the run's first line stands for all of them
        runs += 1
        for name, address in replicas:
            written = COMPOSE_ADDRESS.sub(address, line)
            out.append(re.sub(r"\bdqpose-\d+\b", name, written))
    if not runs:
        raise ValueError(f"{kind}: no server line names a compose replica (dqpose-N:50051)")
    pattern, form = FRONT_END[kind]
    result, n = re.subn(pattern, form.format(listen), "".join(out))
    if n != 1:
        raise ValueError(f"{kind}: expected one front end on :50051, found {n}")
    return result


#: a replica's flags behind a proxy: every client reaches it from the proxy's host, one peer
#: (dqpose.rpc.peers), so the per-peer bounds are the server's (docker/compose.yaml and
#: deploy/kubernetes give the same)
BEHIND_PROXY = ("--max-peer-subscriptions", "256", "--max-peer-streams", "1024")


def free_port(host: str = "127.0.0.1") -> int:
    with socket.socket() as s:
        s.bind((host, 0))
        return s.getsockname()[1]


class Replica:
    """``dqpose serve --replica-name NAME --port PORT`` (0: a free one) in a process, without
    its per-call log lines unless ``call_log``; its JSON log events kept in ``events`` by a
    thread (so that the pipe never fills), each line also written to ``echo`` when given;
    returns once it serves (``address``)."""

    def __init__(self, name: str, *flags: str, port: int = 0, echo=None, start_timeout=60.0,
                 call_log: bool = False):
        self.name, self.flags, self.echo = name, flags, echo
        quiet = () if call_log else ("--no-call-log",)
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "dqpose.cli", "serve", "--host", "127.0.0.1", "--port",
             str(port), "--replica-name", name, *quiet, *flags],
            stderr=subprocess.PIPE, text=True)
        self.events: list[dict] = []
        self.serving: dict = {}
        self._serving = threading.Event()
        threading.Thread(target=self._read, daemon=True).start()
        if not self._serving.wait(start_timeout) or not self.serving:
            self.proc.kill()
            raise RuntimeError(f"replica {name} did not start within {start_timeout:g} s: "
                               f"{self.events}")
        self.port = int(self.serving["address"].rsplit(":", 1)[1])
        self.address = f"127.0.0.1:{self.port}"

    def _read(self) -> None:
        assert self.proc.stderr is not None
        for line in self.proc.stderr:
            if self.echo is not None:
                self.echo.write(line)
                self.echo.flush()
            if line.startswith("{"):
                event = json.loads(line)
                self.events.append(event)
                if event.get("event") == "serving":
                    self.serving = event
                    self._serving.set()
        self._serving.set()         # ended: the waiter sees no address and says so

    def signal(self, sig: int) -> None:
        self.proc.send_signal(sig)

    def stop(self, sig: int | None = None, timeout: float = 10.0) -> None:
        """``sig`` (default SIGKILL) unless it has ended; killed if it has not ended within
        ``timeout`` s after it."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGKILL if sig is None else sig)
        try:
            self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(timeout)


class Proxy:
    """The shipped configuration of ``kind`` from ``config`` (its path) in a process, rewritten by
    :func:`proxy_config` for ``replicas`` and ``listen`` (default a free loopback port);
    ``.target`` is its address. The process's output goes to a log file (``output()``)."""

    def __init__(self, kind: str, config: str, replicas: list[tuple[str, str]],
                 listen: str | None = None, start_timeout: float = 20.0):
        self.kind = kind
        self.target = listen or f"127.0.0.1:{free_port()}"
        self.dir = tempfile.mkdtemp(prefix=f"dqpose-{kind}-")
        with open(config) as f:
            text = proxy_config(kind, f.read(), replicas, self.target)
        path = os.path.join(self.dir, os.path.basename(config))
        with open(path, "w") as f:
            f.write(text)
        if kind == "haproxy":
            argv = [executable(kind), "-db", "-f", path]
        else:
            argv = [executable(kind), "-p", self.dir, "-e", "stderr",
                    "-g", f"daemon off; pid {self.dir}/nginx.pid;", "-c", path]
        self.log = open(os.path.join(self.dir, "log"), "w+")
        self.proc = subprocess.Popen(argv, stdout=self.log, stderr=subprocess.STDOUT,
                                     cwd=self.dir)
        deadline = time.monotonic() + start_timeout
        while not self._listening():
            if self.proc.poll() is not None or time.monotonic() > deadline:
                problem = self.output()
                self.stop()
                raise RuntimeError(f"{kind} did not start on {self.target}: {problem}")
            time.sleep(0.05)

    def _listening(self) -> bool:
        host, port = self.target.rsplit(":", 1)
        with socket.socket() as s:
            return s.connect_ex((host, int(port))) == 0

    def output(self) -> str:
        self.log.flush()
        self.log.seek(0)
        return self.log.read()

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)
        self.log.close()
        shutil.rmtree(self.dir, ignore_errors=True)


def configure(name: str, p) -> None:
    p.description = (
        "Scale-out on this machine: --replicas dqpose servers on free loopback ports (replica "
        "names r1, r2, ...) and HAProxy in front of them on --host:--port, running "
        "docker/haproxy.cfg with its server lines rewritten to the replicas; a world's calls "
        "(Client(world=...)) reach one replica, the rest are balanced per call, and "
        "Client.last_replica says which replica answered. Stop one replica (kill PID) to watch "
        "its worlds move; Ctrl-C stops everything. Needs haproxy (apt-get install -y haproxy) "
        "or nginx.")
    p.add_argument("--replicas", type=int, default=3, help="how many (default: %(default)s)")
    p.add_argument("--host", default="127.0.0.1", help="the proxy's address (default: "
                                                       "%(default)s)")
    p.add_argument("--port", type=int, default=50050,
                   help="the proxy's port (default: %(default)s, compose's cluster port)")
    p.add_argument("--proxy", choices=sorted(PROXIES), default="haproxy",
                   help="the balancer (default: %(default)s)")
    p.add_argument("--config", metavar="PATH",
                   help="its configuration to rewrite (default: docker/haproxy.cfg or "
                        "docker/nginx.conf of the dqpose clone this runs from)")
    p.add_argument("--drain", default="1",
                   help="each replica's --drain, s (default: %(default)s: longer than "
                        "HAProxy's 200 ms health checks)")
    p.set_defaults(func=_run)


def _default_config(proxy: str) -> str:
    """The shipped file of ``proxy`` in the clone this module runs from (editable install)."""
    here = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    return os.path.join(here, "docker", PROXIES[proxy][2])


def _run(args) -> int:
    from dqpose.cli.common import fail
    if not 1 <= args.replicas <= 64:
        return fail("cluster", f"--replicas: must be within 1..64, got {args.replicas}")
    if not 0 < args.port < 65536:
        return fail("cluster", f"--port: must be within 1..65535, got {args.port}")
    config = args.config or _default_config(args.proxy)
    if not os.path.isfile(config):
        return fail("cluster", f"--config {config}: no such file (docker/{PROXIES[args.proxy][2]} "
                               f"of the dqpose repository)")
    why = missing(args.proxy)
    if why:
        return fail("cluster", f"{why}; the replicas need it in front of them")
    return _serve(args, config)


def _serve(args, config: str) -> int:
    """The replicas and the proxy until Ctrl-C or SIGTERM; exit code 0 once all stopped."""
    from dqpose.cli.common import fail
    stop = threading.Event()
    previous = {s: signal.signal(s, lambda *_: stop.set()) for s in (signal.SIGINT,
                                                                     signal.SIGTERM)}
    replicas: list[Replica] = []
    proxy = None
    try:
        for k in range(args.replicas):
            replicas.append(Replica(f"r{k + 1}", *BEHIND_PROXY, "--drain", args.drain,
                                    echo=sys.stderr))
        proxy = Proxy(args.proxy, config, [(r.name, r.address) for r in replicas],
                      f"{args.host}:{args.port}")
        say_err(event="cluster", address=proxy.target, proxy=args.proxy, config=config,
                replicas={r.name: {"address": r.address, "pid": r.proc.pid} for r in replicas})
        print(f"cluster: {args.proxy} on {proxy.target} in front of "
              + ", ".join(f"{r.name} {r.address} (pid {r.proc.pid})" for r in replicas)
              + f"; Client({proxy.target!r}, world='cell-1', reconnect=5.0); Ctrl-C stops it",
              file=sys.stderr, flush=True)
        ended: set[str] = set()
        while not stop.wait(0.5):
            if proxy.proc.poll() is not None:
                return fail("cluster", f"{args.proxy} ended: {proxy.output()[-2000:]}")
            for r in replicas:      # the proxy sends its worlds to the others meanwhile
                if r.name not in ended and r.proc.poll() is not None:
                    ended.add(r.name)
                    say_err(event="replica_ended", replica=r.name, code=r.proc.returncode)
        return 0
    except (OSError, RuntimeError, ValueError) as e:
        return fail("cluster", str(e))
    finally:
        if proxy is not None:
            proxy.stop()
        for r in replicas:
            r.stop(signal.SIGTERM, 30)
        for s, handler in previous.items():
            signal.signal(s, handler)
