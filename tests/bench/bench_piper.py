"""PiPER safety latency: from a fault injected in the simulator (virtual CAN bus, 200 Hz feedback)
to PiperArm noticing it. Prints one table.

    .venv/bin/python -m tests.bench.bench_piper
"""
from __future__ import annotations

import threading
import time
import uuid

import can
import numpy as np

from dqpose import dq
from dqpose.drivers.base import ArmError
from dqpose.drivers.piper import PiperArm
from dqpose.drivers.sim.piper import PiperSim


def _wait_ok(arm: PiperArm) -> None:
    deadline = time.monotonic() + 5.0
    while not arm.status().ok:
        if time.monotonic() > deadline:
            raise RuntimeError("the arm did not recover after clear_faults()")
        time.sleep(0.001)


def main() -> int:
    ch = f"bench-{uuid.uuid4().hex[:6]}"
    b1, b2 = can.Bus(interface="virtual", channel=ch), can.Bus(interface="virtual", channel=ch)
    sim = PiperSim(b1).start()
    arm = PiperArm(b2, watchdog=0.2, stale_after=0.5)
    flag, move = [], []
    try:
        arm.wait_for_feedback(2.0)
        for i in range(60):
            inject = sim.emergency_stop if i % 2 else sim.collide
            t0 = time.perf_counter()
            inject()
            while not (arm.status().emergency_stop or arm.status().protective_stop):
                time.sleep(0.0002)
            flag.append(time.perf_counter() - t0)
            sim.clear_faults()
            _wait_ok(arm)
        for i in range(20):
            sim.max_speed = 0.02
            q0, t0p = dq.to_pose(arm.tool_pose()[1])
            target = dq.from_pose(q0, t0p + [0.03 if i % 2 == 0 else -0.03, 0, 0])
            stamp = {}

            def fire():
                stamp["t"] = time.perf_counter()
                sim.collide()
            threading.Timer(0.1, fire).start()
            try:
                arm.move(target, speed=0.2, accel=1.0, timeout=5.0)
            except ArmError as e:
                if "collision" in str(e):
                    move.append(time.perf_counter() - stamp["t"])
            sim.clear_faults()
            _wait_ok(arm)
    finally:
        arm.close()
        sim.close()
        b1.shutdown()
        b2.shutdown()
    print("| from fault injection to | n | p50 | p95 | max |\n|---|---|---|---|---|")
    for name, v in (("status() flag set", flag), ("running move() raises", move)):
        v = np.array(v) * 1e3
        print(f"| {name} | {len(v)} | {np.percentile(v, 50):.1f} ms | "
              f"{np.percentile(v, 95):.1f} ms | {v.max():.1f} ms |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
