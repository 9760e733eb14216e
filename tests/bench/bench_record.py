"""What recording costs and how fast a recording replays: StreamFuse through the shipped client
into a ``dqpose serve`` process without and with ``--record``, alternating within one run (the
same scene, rate and machine load), then the recording replayed in process at ``--speed max``
with every answer compared byte for byte.

    .venv/bin/python -m tests.bench.bench_record                  # ~2 min
    .venv/bin/python -m tests.bench.bench_record --seconds 600    # a 10-minute recording

Rows: the paced stream (``--rate`` measurements/s, 10 a message, ``--bodies`` bodies, the scene of
``bench_fusion_stream``) against a server without recording and one with it, ``--rounds`` times
each in turn; the added latency of the answers (p50/p99/max, as ``bench_fusion_stream`` measures
it), the server's CPU per message, the recording's size per minute and the messages it dropped.
Then the replay: measurements/s through ``dqpose.rpc.replay`` in process, and whether every answer
was identical.
"""
from __future__ import annotations

import argparse
import glob
import os
import shutil
import sys
import tempfile
import time

import numpy as np

from tests.bench.bench_fusion_stream import PER_MESSAGE, Scene, _cpu_seconds, run
from tests.bench.bench_grpc import ServerProcess


def _children(pid: int) -> list[int]:
    """The processes ``pid`` started (``dqpose serve --record``'s writer)."""
    try:
        with open(f"/proc/{pid}/task/{pid}/children") as f:
            return [int(c) for c in f.read().split()]
    except OSError:
        return []


def put_cost(messages: int, rate: float) -> dict:
    """What a recorded request costs the servicer that records it: ``CallRecord.measurements``
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
            call.measurements(d)
            took[i] = time.perf_counter() - t
        call.end("OK")
        r.close()
        dropped = r.dropped
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    return dict(p50=np.percentile(took, 50) * 1e6, p99=np.percentile(took, 99) * 1e6,
                max=took.max() * 1e6, mean=took.mean() * 1e6, dropped=dropped,
                size=np.mean([len(d) for d in data]))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rate", type=float, default=20000.0, help="measurements/s")
    ap.add_argument("--bodies", type=int, default=100)
    ap.add_argument("--output-rate", type=float, default=1.0, help="answers per body, Hz")
    ap.add_argument("--window", type=float, default=0.1, help="seconds per body")
    ap.add_argument("--seconds", type=float, default=15.0, help="length of each stream")
    ap.add_argument("--rounds", type=int, default=2, help="streams per server, in turn")
    args = ap.parse_args(argv)

    from dqpose.record.reader import read
    from dqpose.rpc import replay

    work = tempfile.mkdtemp(prefix="bench_record_")
    rows: dict[str, list] = {"off": [], "on": []}
    sizes, minutes = [], 0.0
    try:
        for k in range(args.rounds):
            for mode in ("off", "on"):
                scene = Scene(args.bodies, args.rate, seed=k)
                folder = os.path.join(work, f"{mode}{k}")
                extra = ("--record", folder) if mode == "on" else ()
                server = ServerProcess("aio", quiet_log=True, extra=extra)
                try:
                    writer = _children(server.proc.pid)
                    cpu0 = sum(map(_cpu_seconds, writer))
                    r = run(server.target, scene, args.seconds, args.rate / PER_MESSAGE, args,
                            server.rss_mb, server.proc.pid)
                    r["writer_cpu"] = (sum(map(_cpu_seconds, writer)) - cpu0) / r["n"] * 1e6
                    rows[mode].append(r)
                finally:
                    server.stop()      # SIGTERM: the recording is finished
                if mode == "on":
                    sizes.append(sum(os.path.getsize(f) for f in glob.glob(f"{folder}/*.mcap")))
                    minutes += args.seconds / 60
        files = sorted(glob.glob(os.path.join(work, "on0", "*.mcap")))
        t0 = time.perf_counter()
        recordings = [read(f) for f in files]
        t_read = time.perf_counter() - t0
        reports = [replay.replay(r, replay.InProcess()) for r in recordings]
        dropped = sum(d.count for r in recordings for d in r.dropped)
    finally:
        shutil.rmtree(work, ignore_errors=True)

    def pooled(mode, key):
        return float(np.mean([r[key] for r in rows[mode]]))

    print(f"StreamFuse with and without dqpose serve --record (--no-call-log), "
          f"{args.bodies} bodies, {PER_MESSAGE} measurements a message (full covariances), "
          f"{args.rate:.0f} measurements/s paced, output_rate {args.output_rate:g} Hz per body, "
          f"{args.rounds} x {args.seconds:g} s each in turn; latency of the answers after each "
          f"stream's first second (bench_fusion_stream's measure), the mean over the rounds")
    head = ("server", "meas/s", "answers/s", "p50 ms", "p99 ms", "max ms", "server CPU us/msg",
            "writer process CPU us/msg", "MB/min recorded", "dropped")
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    for mode in ("off", "on"):
        mb = f"{sum(sizes) / 1e6 / minutes:.1f}" if mode == "on" else "-"
        writer = f"{pooled(mode, 'writer_cpu'):.0f}" if mode == "on" else "-"
        drops = str(dropped) if mode == "on" else "-"
        print(f"| {'--record' if mode == 'on' else 'no recording'} | "
              f"{pooled(mode, 'measurements'):.0f} | {pooled(mode, 'answers'):.1f} | "
              f"{pooled(mode, 'p50'):.2f} | {pooled(mode, 'p99'):.2f} | "
              f"{max(r['max'] for r in rows[mode]):.1f} | {pooled(mode, 'server_cpu'):.0f} | "
              f"{writer} | {mb} | {drops} |")
    added = pooled("on", "p99") - pooled("off", "p99")
    print(f"added p99: {added:+.2f} ms; per round (off, on): " + ", ".join(
        f"({a['p99']:.2f}, {b['p99']:.2f})" for a, b in zip(rows["off"], rows["on"])))
    requests = sum(r.requests for r in reports)
    seconds = sum(r.seconds for r in reports)
    same = all(r.difference is None for r in reports)
    put = put_cost(20000, args.rate / PER_MESSAGE)
    print()
    print(f"| a request recorded by its servicer ({put['size']:.0f} bytes, "
          f"{args.rate / PER_MESSAGE:.0f}/s, 20,000) | mean us | p50 us | p99 us | max us | "
          f"dropped |")
    print("|---|---|---|---|---|---|")
    print(f"| CallRecord.measurements (frame, buffer, non-blocking pipe write) | "
          f"{put['mean']:.1f} | {put['p50']:.1f} | {put['p99']:.1f} | {put['max']:.0f} | "
          f"{put['dropped']} |")
    print()
    print("| replay (in process, --speed max) | requests | measurements | answers | read s | "
          "replay s | measurements/s | every answer identical |")
    print("|---|---|---|---|---|---|---|---|")
    print(f"| {len(files)} file(s), {args.seconds:g} s recorded | {requests} | "
          f"{requests * PER_MESSAGE} | {sum(r.answers for r in reports)} | {t_read:.2f} | "
          f"{seconds:.2f} | {requests * PER_MESSAGE / seconds:.0f} | "
          f"{'yes' if same else 'NO: ' + str(reports[0].difference)} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
