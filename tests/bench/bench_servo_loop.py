"""Where a 500 Hz servo loop loses its cycles: the interpreter lock, or the machine.

    .venv/bin/python -m tests.bench.bench_servo_loop --seconds 10 --repeats 3

A bare loop of ``URArm.servo`` (``servoL`` + ``waitPeriod``, no executor) on a small line, in a
thread at SCHED_FIFO 20, against the simulated UR at FIFO 30, measured at the simulator (kernel
receive stamps, as ``bench_executor``) and by the loop itself (how late each ``servo()``
returned against its cycle's end). Variants, alternated in each repeat:

* ``monitor``: ``URArm`` as shipped, with its 100 Hz monitor thread (Python);
* ``no monitor``: the monitor thread never runs (its checks made inline), so no other Python
  thread of the process wants the interpreter lock;
* ``monitor + busy thread``: one more Python thread computing 1 ms of every 10 ms, as a feeder
  or a gRPC server in the same process would;
* ``C loop``: ``vcpu_gaps.c`` (compiled here with gcc), no Python at all, FIFO 90 on each CPU:
  how late a real-time thread wakes on this machine, and the gaps while it spins.
"""
from __future__ import annotations

import argparse
import math
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from dqpose import dq
from dqpose.drivers.sim import ur as ursim
from dqpose.drivers.ur import URArm
from tests.bench.bench_executor import realtime


class NoMonitor(URArm):
    """``URArm`` without its monitor thread: the data's freshness is checked inline."""

    def _watch(self):
        return

    def _fault(self, now):
        ts = self._recv.getTimestamp()
        if ts != self._ts:
            self._ts, self._ts_changed = ts, now
        return super()._fault(now)


def run(sim, cls, seconds: float, busy: bool) -> dict:
    arm = cls(sim.host, stale_after=0.5)
    q, p = dq.to_pose(arm.tool_pose()[1])
    stop = threading.Event()

    def work():
        a = np.random.rand(200, 200)
        while not stop.is_set():
            t = time.perf_counter()
            while time.perf_counter() - t < 0.001:
                a.sum()
            time.sleep(0.009)
    if busy:
        threading.Thread(target=work, daemon=True).start()
    mark = sim.log()["next"]
    n = int(seconds * 500)
    late = np.empty(n)

    def loop():
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(20))
        for k in range(n):
            f = 0.5 * (1 - math.cos(2 * math.pi * k / n))
            arm.servo(dq.from_pose(q, p + [0.02 * f, 0.0, 0.0]))
            late[k] = time.monotonic() - arm._pacer._next     # the cycle's end
    th = threading.Thread(target=loop)
    th.start()
    th.join()
    stop.set()
    a = np.array([e["mono"] for e in sim.log(mark, cmd=ursim.SERVOL, keys=["mono"])["entries"]])
    arm.close()
    dt = np.diff(a)
    j = np.abs(dt - 0.002)
    return dict(n=len(a), missed=int(round((a[-1] - a[0]) / 0.002)) + 1 - len(a),
                gt3=int((dt > 0.003).sum()), p50=np.percentile(j, 50) * 1e6,
                p99=np.percentile(j, 99) * 1e6, max=j.max() * 1e6,
                late99=np.percentile(late, 99) * 1e6, latemax=late.max() * 1e6,
                late05=int((late > 0.0005).sum()))


def c_loop(seconds: float) -> list[str]:
    src = Path(__file__).with_name("vcpu_gaps.c")
    exe = Path(tempfile.gettempdir()) / "dqpose_vcpu_gaps"
    subprocess.run(["gcc", "-O2", "-o", str(exe), str(src)], check=True)
    procs = [subprocess.Popen([str(exe), str(cpu), str(seconds), "90"], stdout=subprocess.PIPE,
                              text=True) for cpu in range(os.cpu_count() or 1)]
    return [p.communicate()[0].strip() for p in procs]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args(argv)
    variants = [("monitor", URArm, False), ("no monitor", NoMonitor, False),
                ("monitor + busy thread", URArm, True)]
    print(f"load average {os.getloadavg()[0]:.2f} at the start", file=sys.stderr)
    rows = []
    with ursim.URSimProcess(args=("--max-linear-speed", "5")) as sim:
        realtime(sim.proc.pid, 30)
        for _ in range(args.repeats):
            for name, cls, busy in variants:
                r = run(sim, cls, args.seconds, busy)
                r["name"], r["load"] = name, os.getloadavg()[0]
                rows.append(r)
                print(f"{name}: done", file=sys.stderr, flush=True)
                sim.set_pose(ursim.SimConfig().pose)
                time.sleep(0.2)
    print(f"\nURArm.servo at 500 Hz, {args.seconds:g} s a run; simulator FIFO 30, loop FIFO 20")
    print("| variant | set-points | missed cycles | dt > 3 ms | jitter p50 (µs) | p99 | max "
          "| servo() late p99 (µs) | max | late > 0.5 ms | load |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['name']} | {r['n']} | {r['missed']} | {r['gt3']} | {r['p50']:.0f} "
              f"| {r['p99']:.0f} | {r['max']:.0f} | {r['late99']:.0f} | {r['latemax']:.0f} "
              f"| {r['late05']} | {r['load']:.1f} |")
    print(f"\nC loop (vcpu_gaps.c), {args.seconds * 3:g} s on each CPU at once, load "
          f"{os.getloadavg()[0]:.2f}:")
    for line in c_loop(args.seconds * 3):
        print(f"    {line}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
