"""What recording costs and how fast a recording replays: StreamFuse through the shipped client
into three ``dqpose serve`` processes, two without and one with ``--record``, in many short
rounds of rotating order (the same scene, rate and load within a round), then the recording
replayed whole in process at ``--speed max`` (its rotated files as one run) with every answer
compared byte for byte.

    .venv/bin/python -m tests.bench.bench_record                      # ~6 min
    .venv/bin/python -m tests.bench.bench_record --replay-seconds 600 # and a 10-minute stream

Rows: the paced stream (``--rate`` measurements/s, 10 a message, ``--bodies`` bodies, the scene of
``bench_fusion_stream``); each round streams ``--seconds`` into both servers in turn (which one
first alternates), and the latency of the answers after each stream's first second is kept
(``bench_fusion_stream``'s measure). The servers share one CPU, the client and the writer
process the other (``os.sched_setaffinity``; ``--no-pin``: none), so the rounds differ less by
where the scheduler put them. The added p99 is the p99 of every recorded round's latencies
less the p99 of every unrecorded round's (the first unrecorded server's), with a 95 % bootstrap
interval that resamples whole rounds (each round's streams together: the load they shared is
kept); and, less moved by a few rounds' stalls, the median over rounds of each round's p99
difference, with its bootstrap interval. The same between the two unrecorded servers is the
control: what this machine shows when nothing differs. The target (≤ 0.3 ms) is judged only
when the control's interval lies within ±0.3 ms (the machine resolves a difference that size),
and shown only when the interval lies below it. Then what one recorded request costs its
servicer, and the replay: measurements/s and whether every answer was identical; then the
shipped ``dqpose replay`` in its own process over the whole run, over its first file alone and
over the whole run into a fresh server (``--server``), with each one's peak resident memory (a
replay holds only the open calls and the answers not yet compared, so the peak does not grow
with the recording).
"""
from __future__ import annotations

import argparse
import glob
import os
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from tests.bench.bench_fusion_stream import PER_MESSAGE, Scene, _cpu_seconds, run
from tests.bench.bench_grpc import ServerProcess

if TYPE_CHECKING:
    from dqpose.rpc.replay import Report

#: the target: what recording may add to StreamFuse's p99 at 20,000 measurements/s, ms
TARGET_MS = 0.3


def _children(pid: int) -> list[int]:
    """The processes ``pid`` started (``dqpose serve --record``'s writer)."""
    try:
        with open(f"/proc/{pid}/task/{pid}/children") as f:
            return [int(c) for c in f.read().split()]
    except OSError:
        return []


def cli_replay(paths: list[str], *flags: str) -> tuple[float, float, int]:
    """``dqpose replay [FLAGS] PATHS`` as a user runs it (its own process): seconds, its peak
    resident memory (MB, the kernel's high-water mark) and its exit code."""
    t = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-m", "dqpose.cli", "replay", *flags, *paths],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    return time.perf_counter() - t, usage.ru_maxrss / 1024.0, proc.returncode


def _pin(pid: int, cpus: set[int]) -> None:
    """Every thread of process ``pid`` on ``cpus`` (threads it starts later inherit it)."""
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            os.sched_setaffinity(int(tid), cpus)
        except OSError:
            pass


def added_p99(off: list[np.ndarray], on: list[np.ndarray], resamples: int = 2000,
              seed: int = 0) -> tuple[float, float, float]:
    """p99(on) - p99(off) over the rounds' pooled latencies (ms), and its 95 % bootstrap
    interval: rounds drawn with replacement, each round's two streams together."""
    def diff(idx) -> float:
        return float(np.percentile(np.concatenate([on[i] for i in idx]), 99)
                     - np.percentile(np.concatenate([off[i] for i in idx]), 99))

    k = len(off)
    rng = np.random.default_rng(seed)
    boot = np.array([diff(rng.integers(0, k, k)) for _ in range(resamples)])
    lo, hi = np.percentile(boot, [2.5, 97.5])
    return diff(range(k)), float(lo), float(hi)


def round_p99s(off: list[np.ndarray], on: list[np.ndarray], resamples: int = 2000,
               seed: int = 0) -> tuple[float, float, float]:
    """The median over rounds of each round's p99(on) - p99(off) (ms), and its 95 % bootstrap
    interval: what recording adds to a round's p99, a few rounds' stalls weighing no more than
    any other round."""
    d = np.array([np.percentile(b, 99) - np.percentile(a, 99) for a, b in zip(off, on)])
    rng = np.random.default_rng(seed)
    boot = np.median(d[rng.integers(0, len(d), (resamples, len(d)))], axis=1)
    lo, hi = np.percentile(boot, [2.5, 97.5])
    return float(np.median(d)), float(lo), float(hi)


def verdict(lo: float, hi: float, control: tuple[float, float], rounds: int) -> str:
    """What an interval ``[lo, hi]`` shows about the target, given the control's interval
    between two unrecorded servers: the machine resolves the target's size only when the
    control's interval lies within ±TARGET_MS (load bursts hit some rounds and not others, and
    the intervals over 30 rounds do not cover that well)."""
    if rounds < 10:
        return "not judged: fewer than 10 rounds"
    if not -TARGET_MS <= control[0] <= control[1] <= TARGET_MS:
        return (f"not resolved: two unrecorded servers differ by [{control[0]:+.2f}, "
                f"{control[1]:+.2f}] ms, more than ±{TARGET_MS} ms, at this load")
    if hi <= TARGET_MS:
        return f"shown: the added p99 is <= {TARGET_MS} ms (95 % interval)"
    if lo > TARGET_MS:
        return f"missed: recording adds more than {TARGET_MS} ms at p99 (95 % interval)"
    return (f"not resolved: the 95 % interval [{lo:+.2f}, {hi:+.2f}] ms holds {TARGET_MS} ms")


def put_cost(messages: int, rate: float) -> dict:
    """What a recorded request costs the servicer that records it: ``CallRecord.request``
    timed one by one, ``messages`` of the scene's requests at ``rate`` messages/s, with the writer
    process draining the pipe (the flushes included: they happen inside the puts)."""
    from dqpose.record.recorder import Recorder
    from dqpose.rpc._proto.dqpose.v1 import fusion_pb2 as pb
    from tests.bench.bench_fusion_stream import wire_messages

    data = wire_messages(Scene(100, 20000.0), messages)
    folder = tempfile.mkdtemp(prefix="bench_record_put_")
    try:
        r = Recorder(folder)
        call = r.call("dqpose.v1.Fusion/StreamFuse", pb.FuseStreamRequest, pb.FusedPose)
        took = np.empty(messages)
        t0 = time.perf_counter()
        for i, d in enumerate(data):
            due = t0 + i / rate
            while time.perf_counter() < due:
                time.sleep(0.0002)
            t = time.perf_counter()
            call.request(d)
            took[i] = time.perf_counter() - t
        call.end("OK")
        r.close()
        dropped = r.dropped
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    return dict(p50=np.percentile(took, 50) * 1e6, p99=np.percentile(took, 99) * 1e6,
                max=took.max() * 1e6, mean=took.mean() * 1e6, dropped=dropped,
                size=np.mean([len(d) for d in data]))


#: the three servers, in the order each round starts from, and their rows' names
MODES = ("off", "on", "off2")
NAMES = {"off": "no recording", "on": "--record", "off2": "no recording (control)"}


def _arguments(argv) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rate", type=float, default=20000.0, help="measurements/s")
    ap.add_argument("--bodies", type=int, default=100)
    ap.add_argument("--output-rate", type=float, default=1.0, help="answers per body, Hz")
    ap.add_argument("--window", type=float, default=0.1, help="seconds per body")
    ap.add_argument("--seconds", type=float, default=5.0, help="length of each round's streams")
    ap.add_argument("--rounds", type=int, default=30, help="rounds, each both servers in turn")
    ap.add_argument("--replay-seconds", type=float, default=0.0,
                    help="then one stream this long into the recording server, so that the "
                         "replayed run holds it (600: a 10-minute recording)")
    ap.add_argument("--record-max-mb", type=float, default=256.0,
                    help="the recording server's rotation size")
    ap.add_argument("--no-pin", action="store_true", help="leave the CPUs to the scheduler")
    ap.add_argument("--writer-cpu", choices=("client", "server"), default="client",
                    help="pin the writer process beside the client (default) or the servers")
    ap.add_argument("--cost-only", action="store_true",
                    help="the recording's cost alone, no replay of the recording")
    return ap.parse_args(argv)


@dataclass
class Rounds:
    """What the rounds measured: each server's rows (``run``'s), the writer process's CPU
    seconds a measurement in each recorded round, the load averages and the long stream's
    seconds (0: none)."""
    rows: dict[str, list] = field(default_factory=lambda: {m: [] for m in MODES})
    writer_cpu: list[float] = field(default_factory=list)
    load: list[float] = field(default_factory=list)
    t_long: float = 0.0


def _streams(args, servers: dict, writer: list[int], out: Rounds) -> None:
    """The warm-up, the rounds (each server first, second and third as often) and the long
    stream into the recording server when asked."""
    for mode in MODES:      # warm-up, not counted
        run(servers[mode].target, Scene(args.bodies, args.rate, seed=99), 2.0,
            args.rate / PER_MESSAGE, args, servers[mode].rss_mb)
    for k in range(args.rounds):
        order = MODES[k % 3:] + MODES[:k % 3]
        for mode in order if k % 6 < 3 else order[::-1]:
            s = servers[mode]
            cpu0 = sum(map(_cpu_seconds, writer))
            r = run(s.target, Scene(args.bodies, args.rate, seed=k), args.seconds,
                    args.rate / PER_MESSAGE, args, s.rss_mb, s.proc.pid)
            if mode == "on":
                out.writer_cpu.append((sum(map(_cpu_seconds, writer)) - cpu0) / r["n"])
            out.rows[mode].append(r)
        out.load.append(os.getloadavg()[0])
    if args.replay_seconds > 0:
        t = time.perf_counter()
        run(servers["on"].target, Scene(args.bodies, args.rate, seed=1000),
            args.replay_seconds, args.rate / PER_MESSAGE, args, servers["on"].rss_mb)
        out.t_long = time.perf_counter() - t
        out.load.append(os.getloadavg()[0])


def _rounds(args, folder: str, cpus: list[int], pin: bool) -> Rounds:
    """The three servers, the second recording into ``folder``, placed on the CPUs (when
    ``pin``), through :func:`_streams`; stopped at the end, which finishes the recording."""
    out = Rounds(load=[os.getloadavg()[0]])
    if pin:     # the servers (and the writer they start) inherit the server CPU
        os.sched_setaffinity(0, {cpus[-1]})
    servers = {"off": ServerProcess("aio", quiet_log=True),
               "on": ServerProcess("aio", quiet_log=True, extra=(
                   "--record", folder, "--record-max-mb", str(args.record_max_mb))),
               "off2": ServerProcess("aio", quiet_log=True)}
    writer = _children(servers["on"].proc.pid)
    if pin:
        os.sched_setaffinity(0, {cpus[0]})
        for w in writer:
            _pin(w, {cpus[0] if args.writer_cpu == "client" else cpus[-1]})
    try:
        _streams(args, servers, writer, out)
    finally:
        for s in servers.values():
            s.stop()        # SIGTERM: the recording is finished
        os.sched_setaffinity(0, set(cpus))
    return out


@dataclass
class Replayed:
    """The recording's files and size, its runs, the in-process replay's report and seconds,
    and the CLI's rows (label, files, bytes, whether the whole run, seconds, peak RSS MB, exit
    code)."""
    files: list[str]
    size: int
    found: list
    report: Report
    seconds: float
    cli_rows: list[tuple]


def _replay(folder: str) -> Replayed:
    """The recording replayed whole in process, then by the shipped command."""
    from dqpose.record.reader import runs
    from dqpose.rpc import replay

    files = sorted(glob.glob(os.path.join(folder, "*.mcap")))
    size = sum(os.path.getsize(f) for f in files)
    found = runs([folder])
    t0 = time.perf_counter()
    report = replay.replay(found, replay.InProcess())
    t_replay = time.perf_counter() - t0
    # the shipped command's memory: the whole run, and its first file alone (a replay holds
    # the open calls and the answers not yet compared, so the two peaks are alike)
    cli_rows = [("the whole run", len(files), size, True, *cli_replay([folder])),
                ("its first file alone", 1, os.path.getsize(files[0]), False,
                 *cli_replay(files[:1]))]
    fresh = ServerProcess("aio", quiet_log=True)     # the run fed to a server
    try:
        cli_rows.append(("the whole run into a fresh server (--server)", len(files), size,
                         True, *cli_replay([folder], "--server", fresh.target)))
    finally:
        fresh.stop()
    return Replayed(files, size, found, report, t_replay, cli_rows)


def _print_servers(args, rounds: Rounds, cpus: list[int], pin: bool) -> None:
    """The stream's settings and the three servers' table."""
    rows = rounds.rows

    def pooled(mode, key):
        return float(np.mean([r[key] for r in rows[mode]]))

    placed = ((f"servers on CPU {cpus[-1]}, client and writer on CPU {cpus[0]}"
               if args.writer_cpu == "client" else
               f"servers and writer on CPU {cpus[-1]}, client on CPU {cpus[0]}") if pin
              else "unpinned")
    print(f"StreamFuse without and with dqpose serve --record (--no-call-log), {args.bodies} "
          f"bodies, {PER_MESSAGE} measurements a message (full covariances), {args.rate:.0f} "
          f"measurements/s paced, output_rate {args.output_rate:g} Hz per body; {args.rounds} "
          f"rounds of {args.seconds:g} s into each server in turn; "
          f"{placed}; load {min(rounds.load):.1f}-{max(rounds.load):.1f}")
    head = ("server", "meas/s", "answers/s", "latencies", "p50 ms", "p99 ms (pooled)",
            "p99 ms of a round: min / median / max", "max ms", "server CPU us/msg",
            "writer process CPU us/msg")
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    for mode in MODES:
        lat = np.concatenate([r["lat"] for r in rows[mode]])
        p99s = [r["p99"] for r in rows[mode]]
        writer_us = f"{np.mean(rounds.writer_cpu) * 1e6:.0f}" if mode == "on" else "-"
        print(f"| {NAMES[mode]} | "
              f"{pooled(mode, 'measurements'):.0f} | {pooled(mode, 'answers'):.1f} | {len(lat)} | "
              f"{np.percentile(lat, 50):.2f} | {np.percentile(lat, 99):.2f} | "
              f"{min(p99s):.2f} / {np.median(p99s):.2f} / {max(p99s):.2f} | {lat.max():.1f} | "
              f"{pooled(mode, 'server_cpu'):.0f} | {writer_us} |")


def _print_added(args, rows: dict[str, list]) -> None:
    """What recording adds to the p99, pooled and a round's, against the control, with the
    verdicts on the target; then every round's p99."""
    off = [r["lat"] for r in rows["off"]]
    added, lo, hi = added_p99(off, [r["lat"] for r in rows["on"]])
    same, *control = added_p99(off, [r["lat"] for r in rows["off2"]])
    per_round = round_p99s(off, [r["lat"] for r in rows["on"]])
    per_round_control = round_p99s(off, [r["lat"] for r in rows["off2"]])
    print(f"added p99: {added:+.2f} ms, 95 % interval [{lo:+.2f}, {hi:+.2f}] ms (bootstrap over "
          f"rounds); control (two unrecorded servers): {same:+.2f} ms, [{control[0]:+.2f}, "
          f"{control[1]:+.2f}] ms; target <= {TARGET_MS} ms: "
          f"{verdict(lo, hi, (control[0], control[1]), args.rounds)}")
    m, mlo, mhi = per_round
    c, clo, chi = per_round_control
    print(f"a round's p99, recorded less unrecorded, median over rounds: {m:+.2f} ms, 95 % "
          f"interval [{mlo:+.2f}, {mhi:+.2f}] ms; control {c:+.2f} ms, [{clo:+.2f}, {chi:+.2f}] "
          f"ms; target <= {TARGET_MS} ms: {verdict(mlo, mhi, (clo, chi), args.rounds)}")
    for mode in MODES:
        print(f"p99 ms of each round, {NAMES[mode]}: " + " ".join(
            f"{r['p99']:.1f}" for r in rows[mode]))


def _print_put_cost(args) -> None:
    """:func:`put_cost` at the stream's message rate, measured and printed."""
    put = put_cost(20000, args.rate / PER_MESSAGE)
    print()
    print(f"| a request recorded by its servicer ({put['size']:.0f} bytes, "
          f"{args.rate / PER_MESSAGE:.0f}/s, 20,000) | mean us | p50 us | p99 us | max us | "
          f"dropped |")
    print("|---|---|---|---|---|---|")
    print(f"| CallRecord.request (frame, buffer, non-blocking pipe write) | "
          f"{put['mean']:.1f} | {put['p50']:.1f} | {put['p99']:.1f} | {put['max']:.0f} | "
          f"{put['dropped']} |")


def _print_replay(args, replayed: Replayed, t_long: float) -> None:
    """The in-process replay's table, then the shipped command's."""
    report, files, size = replayed.report, replayed.files, replayed.size
    recorded_s = args.rounds * args.seconds + 2.0 + t_long
    print()
    print("| replay (in process, --speed max, the run's files as one sequence) | files | MB | "
          "MB/min | calls | requests | measurements | answers | s | measurements/s | "
          "every answer identical |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    long = f", {args.replay_seconds:g} s in one stream" if t_long else ""
    same_answers = ("yes" if report.difference is None and not report.cut
                    else f"NO: {report.difference or report.cut}")
    print(f"| {recorded_s:.0f} s recorded{long} | {len(files)} in {len(replayed.found)} run(s) | "
          f"{size / 1e6:.0f} | "
          f"{size / 1e6 / recorded_s * 60:.1f} | {report.calls} | {report.requests} | "
          f"{report.requests * PER_MESSAGE} | {report.answers} | {replayed.seconds:.1f} | "
          f"{report.requests * PER_MESSAGE / replayed.seconds:.0f} | "
          f"{same_answers} |")
    print()
    print("| dqpose replay (the CLI, its own process, --speed max) | files | MB | s | "
          "measurements/s | peak RSS MB (the CLI's) | exit (0: every answer identical) |")
    print("|---|---|---|---|---|---|---|")
    for label, count, nbytes, whole, secs, rss, rc in replayed.cli_rows:
        rate = f"{report.requests * PER_MESSAGE / secs:.0f}" if whole else "-"
        print(f"| {label} | {count} | {nbytes / 1e6:.0f} | {secs:.1f} | {rate} | {rss:.0f} | "
              f"{rc} |")


def main(argv=None) -> int:
    args = _arguments(argv)
    cpus = sorted(os.sched_getaffinity(0))
    pin = not args.no_pin and len(cpus) >= 2
    work = tempfile.mkdtemp(prefix="bench_record_")
    folder = os.path.join(work, "on")
    replayed = None
    try:
        rounds = _rounds(args, folder, cpus, pin)
        if not args.cost_only:
            replayed = _replay(folder)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    _print_servers(args, rounds, cpus, pin)
    _print_added(args, rounds.rows)
    _print_put_cost(args)
    if replayed is None:    # --cost-only
        return 0
    _print_replay(args, replayed, rounds.t_long)
    return 0


if __name__ == "__main__":
    sys.exit(main())
