"""UR driver and simulator numbers: servo lag, command transport latency, achieved servo period,
and how fast URArm notices a protective stop, a frozen stream and a killed controller.

    .venv/bin/python -m tests.bench.bench_ur            # ~20 s
    .venv/bin/python -m tests.bench.bench_ur --quick

Lag is counted in controller cycles (2 ms) from the cycle a set-point arrived in to the first
cycle the simulated arm stood on it; transport is client ``servoL`` call to the simulator's
receipt (both read CLOCK_MONOTONIC, same machine).
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from dqpose.drivers.rotvec import pose_from_rotvec, rotvec_from_pose
from dqpose.drivers.sim import ur as ursim
from dqpose.drivers.ur import URArm


def _ramp(p0, n, distance):
    s = 0.5 - 0.5 * np.cos(np.pi * np.arange(1, n + 1) / n)
    out = np.tile(p0, (n, 1))
    out[:, 0] += distance * s
    return out


def _until(pred, timeout=3.0):
    t0 = time.monotonic()
    while not pred():
        if time.monotonic() - t0 > timeout:
            return float("nan")
        time.sleep(0.0005)
    return time.monotonic() - t0


def _q(xs):
    xs = np.asarray(xs, float)
    return f"median {np.median(xs) * 1e3:7.2f} ms  max {np.max(xs) * 1e3:7.2f} ms  (n={len(xs)})"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args(argv)
    reps = 2 if args.quick else 5
    with ursim.URSimProcess(args=("--max-linear-speed", "5")) as sim:
        arm = URArm(sim.host, watchdog_periods=100)
        home = rotvec_from_pose(arm.tool_pose()[1])
        lags, transport, periods = [], [], []
        for _ in range(reps):
            sim.set_pose(home)
            arm._stream.forget()
            start, tick0 = sim.log()["next"], sim.state()["tick"]
            sent = []
            for p in _ramp(home, 500, 0.05):
                sent.append(time.monotonic())
                arm.servo(pose_from_rotvec(p))
            time.sleep(0.02)
            arm.stop()
            entries = [e for e in sim.log(start)["entries"] if e["cmd"] == ursim.SERVOL]
            lags.extend(ursim.servo_lag_cycles(entries, sim.history(tick0)))
            if len(entries) == len(sent):
                transport.extend(e["mono"] - t for e, t in zip(entries, sent))
            periods.extend(np.diff(sent))
        lags = np.asarray(lags)
        print(f"servoL through URArm at 500 Hz, {reps} x 1 s:")
        values, counts = np.unique(lags, return_counts=True)
        print(f"  lag (cycles): {dict(zip(values.tolist(), counts.tolist()))}")
        print(f"  transport servo() -> simulator: {_q(transport)}")
        print(f"  servo() period: mean {np.mean(periods) * 1e3:.3f} ms, "
              f"p99 {np.percentile(periods, 99) * 1e3:.3f} ms, max {np.max(periods) * 1e3:.3f} ms")

        pstop = []
        for _ in range(reps):
            sim.protective_stop(True)
            pstop.append(_until(lambda: arm.status().protective_stop))
            sim.protective_stop(False)
            _until(lambda: not arm.status().protective_stop)
            arm.recover()
        print(f"protective stop -> URArm.status(): {_q(pstop)}")
        stale = []
        for _ in range(reps):
            sim.call("pause_stream", seconds=0.4)
            stale.append(_until(lambda: not arm.status().connected))
            _until(lambda: arm.status().connected)
            arm.recover()
        print(f"frozen stream -> URArm.status(): {_q(stale)} (stale_after {arm.stale_after} s)")
        t0 = time.monotonic()
        sim.kill()
        _until(lambda: not arm.status().connected)
        killed = time.monotonic() - t0       # SIGKILL sent until URArm reports it
        print(f"killed controller -> URArm.status(): {_q([killed])}")
        arm.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
