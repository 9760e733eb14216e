"""A cluster on 127.0.0.1: ``dqpose serve`` replicas (processes) behind a real HAProxy or nginx
running the shipped config (docker/haproxy.cfg, docker/nginx.conf) with the replicas' and the
front end's addresses put in place of the compose names; ``WorldLoad``, one world's producers and
subscriber through it (the cluster test's and bench_cluster's)."""
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

from dqpose.rpc.client import Client
from tests._polling import wait_until
from tests.rpc.test_world_service import SOURCES, measurements

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
DOCKER = os.path.join(ROOT, "docker")
#: the executable each proxy runs as, and the Debian package that has it (.ci/run installs them)
PROXIES = {"haproxy": ("haproxy", "haproxy"), "nginx": ("nginx", "nginx-light")}


def missing(proxy: str) -> str | None:
    """Why ``proxy`` cannot run here (the package to install), or None."""
    exe, package = PROXIES[proxy]
    if shutil.which(exe) or os.path.exists(f"/usr/sbin/{exe}"):
        return None
    return f"{exe} is not installed (apt-get install {package}; .ci/run does)"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Replica:
    """``dqpose serve --replica-name NAME`` on a free port; its standard error is read by a
    thread (JSON events kept in ``events``) so that the pipe never fills."""

    def __init__(self, name: str, *flags: str, port: int = 0):
        self.name, self.flags = name, flags
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "dqpose.cli", "serve", "--port", str(port), "--replica-name",
             name, "--no-call-log", *flags], cwd=ROOT, stderr=subprocess.PIPE, text=True)
        self.events: list[dict] = []
        self._serving = threading.Event()
        threading.Thread(target=self._read, daemon=True).start()
        if not self._serving.wait(60):
            self.proc.kill()
            raise RuntimeError(f"replica {name} did not start: {self.events}")
        self.port = int(self.serving["address"].rsplit(":", 1)[1])
        self.address = f"127.0.0.1:{self.port}"

    def _read(self) -> None:
        assert self.proc.stderr is not None
        for line in self.proc.stderr:
            if line.startswith("{"):
                event = json.loads(line)
                self.events.append(event)
                if event.get("event") == "serving":
                    self.serving = event
                    self._serving.set()

    def signal(self, sig: int) -> None:
        self.proc.send_signal(sig)

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGKILL)
        self.proc.wait(10)


class Proxy:
    """The shipped config of ``kind`` ("haproxy" or "nginx") in a process, in front of
    ``addresses`` (at most as many as the config has replicas; the lines of the others are left
    out), listening on ``.target``."""

    def __init__(self, kind: str, addresses: list[str]):
        self.kind = kind
        self.port = free_port()
        self.target = f"127.0.0.1:{self.port}"
        self.dir = tempfile.mkdtemp(prefix=f"dqpose-{kind}-")
        name = "haproxy.cfg" if kind == "haproxy" else "nginx.conf"
        with open(os.path.join(DOCKER, name)) as f:
            text = f.read()
        names = sorted(set(re.findall(r"dqpose-\d+:50051", text)))
        assert 1 <= len(addresses) <= len(names), f"{name} has {len(names)} replicas"
        for unused in names[len(addresses):]:
            text = "".join(line for line in text.splitlines(True) if unused not in line)
        for compose_name, address in zip(names, addresses):
            text = text.replace(compose_name, address)
        if kind == "haproxy":
            text, n = re.subn(r"bind :50051", f"bind {self.target}", text)
            argv = ["haproxy", "-db", "-f"]
        else:
            text, n = re.subn(r"listen 50051", f"listen {self.target}", text)
            argv = ["nginx", "-p", self.dir, "-e", "stderr",
                    "-g", f"daemon off; pid {self.dir}/nginx.pid;", "-c"]
        assert n == 1, f"{name}: no front end on :50051"
        path = os.path.join(self.dir, name)
        with open(path, "w") as f:
            f.write(text)
        self.log = open(os.path.join(self.dir, "log"), "w+")
        self.proc = subprocess.Popen(argv + [path], stdout=self.log, stderr=subprocess.STDOUT,
                                     cwd=self.dir)
        assert wait_until(self._listening, timeout=20, poll=0.05), \
            f"{kind} not listening on {self.target}: {self.output()}"

    def _listening(self) -> bool:
        assert self.proc.poll() is None, f"{self.kind} ended: {self.output()}"
        with socket.socket() as s:
            return s.connect_ex(("127.0.0.1", self.port)) == 0

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


class Cluster:
    """Three replicas (r1, r2, r3) behind one proxy."""

    def __init__(self, kind: str, *flags: str):
        self.replicas: list[Replica] = []
        self.proxy = None
        try:
            for i in range(3):
                self.replicas.append(Replica(f"r{i + 1}", *flags))
            self.proxy = Proxy(kind, [r.address for r in self.replicas])
        except BaseException:
            self.stop()
            raise

    def replica(self, name: str) -> Replica:
        return next(r for r in self.replicas if r.name == name)

    def restart(self, name: str) -> Replica:
        """Replica ``name`` (which has exited) started again on its port, as an orchestrator
        restarts it: the proxy's configuration stays as it is."""
        k = next(i for i, r in enumerate(self.replicas) if r.name == name)
        old = self.replicas[k]
        assert old.proc.poll() is not None, f"replica {name} still runs"
        self.replicas[k] = Replica(name, *old.flags, port=old.port)
        return self.replicas[k]

    def stop(self) -> None:
        if self.proxy is not None:
            self.proxy.stop()
        for r in self.replicas:
            r.stop()


def wait(seconds: float) -> None:
    """A pause the proxies' timers need (a health check's interval), not a bound on anything."""
    time.sleep(seconds)


PERIOD = 0.1     # s between one producer's batches (measurement time is the clock's)


class WorldLoad:
    """One world through the proxy: its client (configured, ``reconnect``), two producers
    (cam1, cam2) publishing the box at the clock's time, a subscriber; every ack and answer kept
    with its arrival time, every error raised kept."""

    def __init__(self, target: str, name: str, t0: float, stop: threading.Event):
        self.name, self.t0, self.stop = name, t0, stop
        self.client = Client(target, world=name, reconnect=10.0)
        self.client.configure_world(SOURCES, window=1.0)
        self.sent: dict[str, list[float]] = {"cam1": [], "cam2": []}
        self.acks: dict[str, list] = {"cam1": [], "cam2": []}
        self.answers: list = []
        self.errors: list[str] = []
        self.closing = False
        self.producers = [threading.Thread(target=self._produce, args=(s, k), daemon=True)
                          for k, s in enumerate(self.sent)]
        self.watcher = threading.Thread(target=self._watch, daemon=True)
        for t in [self.watcher, *self.producers]:
            t.start()

    def _produce(self, source: str, seed: int) -> None:
        def batches():
            k = 0
            while not self.stop.is_set():
                t = round(time.monotonic() - self.t0, 3)
                self.sent[source].append(t)
                yield measurements(source, [t], 1000 * seed + k)
                k += 1
                self.stop.wait(PERIOD)

        try:
            for a in self.client.publish(batches(), producer=source):
                self.acks[source].append((time.monotonic(), a))
        except Exception as e:          # noqa: BLE001 (every failure is the finding)
            self.errors.append(f"{self.name} {source}: {e}")

    def _watch(self) -> None:
        try:
            for a in self.client.subscribe(["box"], rate_hz=1 / PERIOD):
                self.answers.append((time.monotonic(), a))
        except Exception as e:          # noqa: BLE001
            if not self.closing:
                self.errors.append(f"{self.name} subscriber: {e}")

    def answered_after(self, t: float) -> bool:
        return (any(at > t for at, _ in self.answers)
                and all(any(at > t for at, _ in acks) for acks in self.acks.values()))

    def missing(self, t: float) -> str:
        """What has not answered since ``t``."""
        late = [f"{s} acks" for s, acks in self.acks.items() if not any(at > t for at, _ in acks)]
        late += [] if any(at > t for at, _ in self.answers) else ["subscriber"]
        return f"{self.name}: {', '.join(late)} {self.errors}"

    def end(self) -> None:
        """Producers finish (every batch acked), then the subscriber is closed."""
        for p in self.producers:
            p.join(30)
        self.closing = True
        self.client.close()
        self.watcher.join(30)
