"""Ctrl-C, from the signal to the exit: each command that drives an arm, and ``dqpose sim ur``,
run as a terminal runs it (its own process group) and interrupted once (SIGINT to the group) when
its arm moves, ``--runs`` times; one table.

    .venv/bin/python -m tests.bench.bench_interrupt                  # 3 runs each, ~2 min
    .venv/bin/python -m tests.bench.bench_interrupt --runs 5 --only demo
    .venv/bin/python -m tests.bench.bench_interrupt --runs 1 --breakdown

A row: the command; the load average before its first run and after its last; the arm's first
stop command at the controller after the signal (ms; its simulator's log, the kernel's receive
stamps), and whether any motion command came after it; the exit after the signal (s, min /
median / max); the slowdown of CPU-bound work meanwhile (tests/cli/_interrupt.Slowdown: 1 on an
idle core). ``--breakdown``: every process of the command (itself, its arm's process, its
simulators) runs with a profile hook, and after the table come, per process, the calls that took
15 ms or more, ended after the signal and began at most 0.5 s before it (start and end in
seconds from the signal), and when the process had run its last exit handler; the hook slows
Python code down, so the table of a ``--breakdown`` run is not the command's own.
"""
from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import threading
from pathlib import Path

from dqpose.drivers.sim.ur import (
    MOVEL,
    SERVO_STOP,
    SERVOL,
    SPEED_STOP,
    STOP_SCRIPT,
    STOPJ,
    STOPL,
)
from tests.cli._interrupt import Command, SimWatch, sim_host

STOPS = (SERVO_STOP, SPEED_STOP, STOPL, STOPJ, STOP_SCRIPT)
MOTION = (SERVOL, MOVEL)

# name -> (argv given a scratch folder, the arm moving: (command, SimWatch) -> bool, or None)
COMMANDS = {
    "demo fusion": (lambda d: ("demo", "fusion", "--plot", f"{d}/d.png"),
                    lambda cmd, w: w.count(SERVOL) >= 200),
    "demo trajectory": (lambda d: ("demo", "trajectory", "--trajectory-plot", f"{d}/d.png"),
                        lambda cmd, w: w.count(SERVOL) >= 200),
    "handeye capture": (lambda d: ("handeye", "capture", f"{d}/calib", "--views", "15"),
                        lambda cmd, w: w.count(MOVEL) >= 3),
    "serve --sims --arm ur=ur:sim": (
        lambda d: ("serve", "--sims", "--port", "0", "--arm", "ur=ur:sim"),
        lambda cmd, w: '"event": "serving"' in cmd.stderr),
    "sim ur": (lambda d: ("sim", "ur", "--host", "127.0.0.251"), None),
}

# The profile hook of --breakdown: each call of 15 ms or more, per thread, with its start and
# end on CLOCK_MONOTONIC, appended to DQPOSE_BREAKDOWN.<pid>; the last exit handler's time.
HOOK = '''
import atexit, os, sys, threading, time
_f = open(os.environ["DQPOSE_BREAKDOWN"] + f".{os.getpid()}", "a", buffering=1)
_f.write("# " + " ".join(sys.orig_argv[1:])[:160] + "\\n")
_local, _now = threading.local(), time.monotonic
def _hook(frame, event, arg):
    st = _local.__dict__.setdefault("st", [])
    if event in ("call", "c_call"):
        st.append(_now())
    elif st:
        t0, t1 = st.pop(), _now()
        if t1 - t0 >= 0.015:
            if event == "return":
                c = frame.f_code
                name = f"{c.co_qualname} ({'/'.join(c.co_filename.split('/')[-2:])})"
            else:
                name = getattr(arg, "__qualname__", None) or repr(arg)
            _f.write(f"{t0:.4f} {t1:.4f} {len(st)} {threading.current_thread().name}|{name}\\n")
sys.setprofile(_hook)
threading.setprofile(_hook)
atexit.register(lambda: _f.write(f"{_now():.4f} exit handlers done\\n"))
'''


def _load() -> float:
    with open("/proc/loadavg") as f:
        return float(f.read().split()[0])


def run_once(name: str, scratch: str) -> dict:
    argv, moving = COMMANDS[name]
    cmd = Command(*argv(scratch))
    try:
        watch = None
        if moving is None:
            cmd.wait_for(lambda: "ursim" in cmd.stdout, "the simulator ready")
        else:
            _, host = sim_host(cmd)
            watch = SimWatch(host)
            cmd.wait_for(lambda: moving(cmd, watch), "the arm moving")
        cmd.interrupt()
        code = cmd.wait()
        stop, moved = None, False
        if watch is not None:
            watch.wait_gone()
            after = [e for e in watch.entries if e["mono"] >= cmd.interrupted_at]
            k = next((i for i, e in enumerate(after) if e["cmd"] in STOPS), None)
            if k is not None:
                stop = after[k]["mono"] - cmd.interrupted_at
                moved = any(e["cmd"] in MOTION for e in after[k:])
        return {"code": code, "stop": stop, "moved": moved, "exit": cmd.exit_after,
                "slowdown": cmd.slowdown, "at": cmd.interrupted_at}
    finally:
        cmd.kill()


def _ms(values) -> str:
    v = [1e3 * x for x in values if x is not None]
    return f"{min(v):.1f} / {statistics.median(v):.1f} / {max(v):.1f}" if v else "-"


#: s before the signal a call may have begun and still be shown by --breakdown
RECENT = 0.5


def breakdown(folder: str, signal_at: float) -> None:
    for path in sorted(Path(folder).glob("trace.*")):
        lines = path.read_text().splitlines()
        print(f"\n{path.suffix[1:]}: {lines[0][2:] if lines else ''}")
        calls = []
        for line in lines[1:]:
            t0, rest = line.split(" ", 1)
            if rest == "exit handlers done":
                calls.append((float(t0), None, 0, rest))
                continue
            t1, depth, what = rest.split(" ", 2)
            # what ran on after the signal, but not the threads' and processes' own lives
            if float(t1) >= signal_at and float(t0) >= signal_at - RECENT:
                calls.append((float(t0), float(t1), int(depth), what))
        top = min((c[2] for c in calls if c[1] is not None), default=0)
        for t0, t1, depth, what in sorted(calls):
            if t1 is None:
                print(f"  {t0 - signal_at:+8.3f}           {what}")
            else:
                print(f"  {t0 - signal_at:+8.3f} {t1 - signal_at:+8.3f} "
                      f"{'  ' * min(depth - top, 12)}{what}")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--only", help="rows whose command has this text")
    ap.add_argument("--breakdown", action="store_true",
                    help="profile every process of the command; where the time went")
    args = ap.parse_args(argv)
    names = [n for n in COMMANDS if not args.only or args.only in n]
    traces = []
    rows = []
    for name in names:
        load0, runs = _load(), []
        for _ in range(args.runs):
            scratch = tempfile.mkdtemp(prefix="bench-interrupt-")
            if args.breakdown:
                Path(scratch, "sitecustomize.py").write_text(HOOK)
                os.environ["PYTHONPATH"] = scratch
                os.environ["DQPOSE_BREAKDOWN"] = f"{scratch}/trace"
            try:
                runs.append(run_once(name, scratch))
            finally:
                os.environ.pop("PYTHONPATH", None)
                os.environ.pop("DQPOSE_BREAKDOWN", None)
            traces.append((name, scratch, runs[-1]["at"]))
        rows.append((name, load0, _load(), runs))
    print(f"{'command':30s} {'load':>10s} {'codes':>8s} {'stop after, ms':>22s} "
          f"{'moved':>5s} {'exit after, s':>20s} {'slowdown':>10s}")
    for name, load0, load1, runs in rows:
        codes = ",".join(sorted({str(r["code"]) for r in runs}))
        ex = [r["exit"] for r in runs]
        print(f"{name:30s} {load0:4.1f}-{load1:<5.1f} {codes:>8s} "
              f"{_ms([r['stop'] for r in runs]):>22s} "
              f"{'yes' if any(r['moved'] for r in runs) else 'no':>5s} "
              f"{min(ex):6.3f} / {statistics.median(ex):5.3f} / {max(ex):5.3f} "
              f"{max(r['slowdown'] for r in runs):10.2f}")
    if args.breakdown:
        for name, scratch, at in traces:
            print(f"\n=== {name} (times in s from the signal)")
            breakdown(scratch, at)


if __name__ == "__main__":
    threading.current_thread().name = "bench"
    main()
