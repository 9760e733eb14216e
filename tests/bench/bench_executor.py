"""Executor on the simulated UR at 500 Hz: period jitter and missed cycles measured at the
simulator, the stop after a cancel, and tracking error; idle and while 8 client processes call
`Blend` on a real server on this machine.

    .venv/bin/python -m tests.bench.bench_executor                 # 60 s per row (~4 min)
    .venv/bin/python -m tests.bench.bench_executor --seconds 10 --executor thread

Rows: idle; 8 Blend clients on a server in its own process (`dqpose serve`); 8 Blend clients on
a server in this process, the one that feeds the executor (what the Execute RPC does); optionally
(`--rows ...,in-process-switch`) the same with `sys.setswitchinterval(--switch)`.

`--executor process` (the default): the arm is opened with `drivers.open_arm(..., process=True)`
and the control loop runs in the arm's own process, every thread of which runs SCHED_FIFO at
`--executor-realtime` (the simulator's at `--sim-realtime`, above it, as a controller's loop
would be); the clients, the server and this process keep ordinary scheduling. `--executor
thread`: the loop in a thread of this process, as before (only that thread real-time).

The motion: a smooth closed loop (x, y and a turn about z, zero velocity at both ends), sampled
at 500 Hz and pushed 0.1 s at a time, at most `--ahead` (2 s) ahead, from a feeder thread, as a
network stream would. Jitter is |dt - 2 ms| between the arrivals of consecutive set-points at the
simulator (the kernel's receive stamps of their packets, on CLOCK_MONOTONIC, the clock this
process reads; the column "read p99" is the same from when the simulator's Python thread had read
each one, which adds that thread's own delays);
missed cycles are the controller cycles of the run that got no set-point
(round(span / 2 ms) + 1 - set-points). Tracking error is the distance between the commanded
pose of a cycle and the actual pose read right after it (the simulated controller follows 2
cycles late), and the same against the commanded pose of 2 cycles before.
"""
from __future__ import annotations

import argparse
import math
import sys
import threading
import time

import numpy as np

from dqpose import dq, drivers
from dqpose.drivers.executor import Executor, Result
from dqpose.drivers.sim import ur as ursim

LAG = 2     # the simulator's servo lag in cycles (SimConfig.servo_lag)
EXECUTOR_REALTIME = 20      # --executor-realtime


def loop_plan(start: np.ndarray, seconds: float, rate: float, loop: float = 2.0):
    """A closed loop from ``start`` and back, ``seconds`` long (whole loops of ``loop`` s):
    3 cm in x, 1.5 cm in y, 0.1 rad about base z; at most 0.1 m/s, 0.3 m/s^2, 0.32 rad/s,
    1 rad/s^2, all from rest to rest."""
    n = max(1, round(seconds / loop))
    t = np.arange(int(round(n * loop * rate)) + 1) / rate
    w = 2 * math.pi / loop
    q0, p0 = dq.to_pose(start)
    d = np.stack([0.03 * (1 - np.cos(w * t)), 0.015 * (1 - np.cos(2 * w * t)) / 2,
                  np.zeros_like(t)], axis=1)
    a = 0.1 * (1 - np.cos(w * t))
    rz = np.stack([np.cos(a / 2), 0 * a, 0 * a, np.sin(a / 2)], axis=1)
    rot = dq.mul(dq.from_pose(rz, np.zeros_like(d)), dq.from_pose(q0, np.zeros(3)))
    return t, dq.from_pose(dq.to_pose(rot)[0], p0 + d)


AHEAD = 2.0     # --ahead


def feed(ex: Executor, t, poses, chunk: float = 0.1) -> None:
    ahead = AHEAD
    k = max(1, int(round(chunk / ex.period)))
    for i in range(0, len(t), k):
        while ex.buffered > ahead and not ex.done:
            time.sleep(chunk / 4)
        if ex.done:
            return
        ex.push(t[i:i + k], poses[i:i + k])
    ex.finish()


def log_end(sim) -> int:
    """Where the simulator's log ends, without fetching it (after a long run, all of it is tens
    of thousands of entries: long enough for a 0.5 s test motion to run out meanwhile)."""
    return sim.log(1 << 62)["next"]


def run_once(sim, arm, seconds: float) -> dict:
    start = arm.tool_pose()[1]
    t, poses = loop_plan(start, seconds, 1.0 / arm.period)
    mark = log_end(sim)
    fb = []
    ex = Executor(arm, callback=fb.append, stall_timeout=5.0, realtime=EXECUTOR_REALTIME)
    feeder = threading.Thread(target=feed, args=(ex, t, poses), daemon=True)
    feeder.start()
    arrivals = []
    fetched = time.monotonic()
    while ex.wait(2.0) is None:
        if not feeder.is_alive() and ex.sent == 0 and not ex.done:
            raise RuntimeError("the first push failed (see the feeder's error above)")
        # The simulator keeps 50,000 log entries (100 s at 500 Hz): fetched once a minute, as
        # decoding thousands of them holds this process's GIL for milliseconds, which the
        # executor's thread would wait for and the jitter would count.
        if time.monotonic() - fetched < 60.0:
            continue
        fetched = time.monotonic()
        got = sim.log(mark, cmd=ursim.SERVOL, keys=["mono", "read"])
        arrivals += [(e["mono"], e["read"]) for e in got["entries"]]
        mark = got["next"]
    feeder.join()
    arrivals += [(e["mono"], e["read"])
                 for e in sim.log(mark, cmd=ursim.SERVOL, keys=["mono", "read"])["entries"]]
    # the plan's set-points only: the settle holds after the end are not paced by a plan
    a, read = np.asarray(arrivals)[:len(t)].T
    dt = np.diff(a)
    jitter = np.abs(dt - arm.period)
    missed = int(round((a[-1] - a[0]) / arm.period)) + 1 - len(a)
    ok = [f for f in fb if f.result == Result.OK and f.actual is not None]
    err = np.array([dq.to_pose(f.actual)[1] - dq.to_pose(f.commanded)[1] for f in ok])
    lagged = np.array([dq.to_pose(f.actual)[1] - dq.to_pose(g.commanded)[1]
                       for f, g in zip(ok[LAG:], ok)])
    return {"result": ex.result.name + (" (realtime)" if ex.realtime else ""), "n": len(a),
            "jitter": jitter,
            "read_jitter": np.abs(np.diff(read) - arm.period), "missed": missed,
            "late": int(np.sum(dt > 1.5 * arm.period)), "track": np.linalg.norm(err, axis=1),
            "track_lag": np.linalg.norm(lagged, axis=1)}


def cancel_latency(sim, arm, reps: int) -> np.ndarray:
    """cancel() to the servo stop's arrival at the simulator, on a moving arm."""
    out = []
    for _ in range(reps):
        start = arm.tool_pose()[1]
        t, poses = loop_plan(start, 2.0, 1.0 / arm.period)
        ex = Executor(arm, realtime=EXECUTOR_REALTIME)
        mark = log_end(sim)
        ex.push(t[:250], poses[:250])        # 0.5 s into a 2 s loop: moving
        while ex.sent < 150:
            time.sleep(0.005)
        t_cancel = time.monotonic()
        ex.cancel()
        ex.wait(5)
        # this cancel's stop: the first the simulator read after it (an earlier stop read late,
        # on a loaded machine, is not it); timed by its kernel stamp
        deadline, stop = time.monotonic() + 1.0, None
        while stop is None and time.monotonic() < deadline:
            stops = sim.log(mark, cmd=ursim.SERVO_STOP, keys=["mono", "read"])["entries"]
            stop = next((e for e in stops if e["read"] > t_cancel), None)
            time.sleep(0.01)
        out.append(stop["mono"] - t_cancel if stop else math.nan)
        sim.set_pose(ursim.SimConfig().pose)
        time.sleep(0.05)
    return np.asarray(out)


def realtime(pid: int, priority: int) -> None:
    """Every thread of ``pid`` to SCHED_FIFO at ``priority`` (threads it starts later inherit);
    where that is not permitted, says so and leaves them as they are."""
    import os
    try:
        for tid in os.listdir(f"/proc/{pid}/task"):
            os.sched_setscheduler(int(tid), os.SCHED_FIFO, os.sched_param(priority))
    except (AttributeError, OSError) as e:
        print(f"the simulator runs with ordinary scheduling ({e})", file=sys.stderr)


def renice(pid: int, nice: int) -> None:
    """Every thread of ``pid`` to ``nice`` (Linux nice values are per thread; below 0 needs
    root)."""
    import os
    for tid in os.listdir(f"/proc/{pid}/task"):
        os.setpriority(os.PRIO_PROCESS, int(tid), nice)


def _us(x, q):
    return f"{np.percentile(x, q) * 1e6:.0f}"


def open_arm(sim, process: bool, priority: int):
    arm = drivers.open_arm(f"ur:{sim.host}", process=process, stale_after=0.5)
    if process and priority:
        realtime(arm.pid, priority)     # the arm's own threads too: its data must keep coming
    return arm


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=60.0, help="length of each run (default 60)")
    ap.add_argument("--clients", type=int, default=8)
    ap.add_argument("--switch", type=float, default=0.0005,
                    help="GIL switch interval (s) for the last row (default 0.0005)")
    ap.add_argument("--cancels", type=int, default=5)
    ap.add_argument("--rows", default="idle,server-process,in-process",
                    help="which rows to run (comma-separated)")
    ap.add_argument("--sim-realtime", type=int, default=30, metavar="PRIO",
                    help="SCHED_FIFO priority for the simulator's threads, as a real controller "
                         "runs its loop in real time (0: ordinary scheduling; default 30, needs "
                         "root); the executor asks for its own (Executor realtime=20)")
    ap.add_argument("--executor-realtime", type=int, default=20, metavar="PRIO",
                    help="Executor(realtime=PRIO); 0: ordinary scheduling")
    ap.add_argument("--ahead", type=float, default=2.0,
                    help="how far (s) the feeder keeps the buffer ahead of the arm (default 2; "
                         "the Execute RPC pushes the whole plan at once)")
    ap.add_argument("--executor", choices=("process", "thread"), default="process",
                    help="where the control loop runs (default: the arm's own process)")
    ap.add_argument("--nice", type=int, default=None,
                    help="once the clients run, set the simulator and this process (every "
                         "thread) to this nice value, e.g. -10 (root): the control path ahead of "
                         "the load")
    return ap


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    from tests.bench.bench_grpc import ServerProcess, python_clients
    from tests.rpc._grpc_server import ServerThread

    rows = []
    global EXECUTOR_REALTIME, AHEAD
    EXECUTOR_REALTIME = args.executor_realtime or None
    AHEAD = args.ahead
    with ursim.URSimProcess(args=("--max-linear-speed", "5")) as sim:
        if args.sim_realtime:
            realtime(sim.proc.pid, args.sim_realtime)
        process = args.executor == "process"
        arm = open_arm(sim, process, args.executor_realtime)
        for name in args.rows.split(","):
            server, load, calls = None, None, []
            default_switch = sys.getswitchinterval()
            if name == "server-process":
                server = ServerProcess("aio", quiet_log=True)
            elif name.startswith("in-process"):
                server = ServerThread()
                if name.endswith("switch"):
                    sys.setswitchinterval(args.switch)
            if server is not None:
                load = threading.Thread(target=lambda: calls.append(python_clients(
                    server.target, args.clients, args.seconds + args.cancels + 6)), daemon=True)
                load.start()
                time.sleep(3.0)             # clients spawned and calling
            if args.nice is not None:
                import os
                renice(sim.proc.pid, args.nice)
                renice(os.getpid(), args.nice)
                if process:
                    renice(arm.pid, args.nice)
            try:
                r = run_once(sim, arm, args.seconds)
                r["cancel"] = cancel_latency(sim, arm, args.cancels)
            except Exception as e:      # a row that breaks is a result too: say how
                r = {"result": f"failed: {e}"}
                try:
                    arm.close()
                except Exception:
                    pass
                arm = open_arm(sim, process, args.executor_realtime)
            if load is not None:
                load.join()
                r["calls"] = calls[0][0] if calls else math.nan
                server.stop()
            sys.setswitchinterval(default_switch)
            r["name"] = name
            r["load"] = __import__("os").getloadavg()[0]
            rows.append(r)
            print(f"{name}: done ({r['result']}, {r.get('n')} set-points)", file=sys.stderr,
                  flush=True)
        arm.close()

    _print_table(args, rows)
    return 0


def _print_table(args, rows) -> None:
    """The one table of the rows run."""
    import os
    print(f"\nExecutor ({args.executor}) on the simulated UR, 500 Hz, {args.seconds:g} s per row; "
          f"{args.clients} Blend client processes where a server is named; simulator "
          f"{'FIFO %d' % args.sim_realtime if args.sim_realtime else 'ordinary'}, executor "
          f"{'FIFO %d' % args.executor_realtime if args.executor_realtime else 'ordinary'}; "
          f"load average at the end {os.getloadavg()[0]:.2f}")
    print("| row | result | set-points | missed cycles | dt > 3 ms | jitter p50 (µs) | p99 | max "
          "| read p99 (µs) | cancel → stop at sim, max (ms) | tracking p50 / p99 / max (mm) "
          "| at 2-cycle lag, max (mm) | Blend calls/s | load |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        if "jitter" not in r:
            print(f"| {r['name']} | {r['result']} |" + " |" * 11 + f" {r['load']:.1f} |")
            continue
        tr, tl = r["track"] * 1e3, r["track_lag"] * 1e3
        print(f"| {r['name']} | {r['result']} | {r['n']} | {r['missed']} | {r['late']} "
              f"| {_us(r['jitter'], 50)} | {_us(r['jitter'], 99)} | {r['jitter'].max() * 1e6:.0f} "
              f"| {_us(r['read_jitter'], 99)} | {np.nanmax(r['cancel']) * 1e3:.2f} "
              f"| {np.median(tr):.3f} / {np.percentile(tr, 99):.3f} / {tr.max():.3f} "
              f"| {tl.max():.4f} | {r.get('calls', math.nan):.0f} | {r['load']:.1f} |")


if __name__ == "__main__":
    raise SystemExit(main())
