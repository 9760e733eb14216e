"""A bystander beside the heaviest requests: each of the reliability probe's heavy requests, and
each request at the largest size the server's limits allow (``service/limits.py``), sent to one
``dqpose serve`` process (its own process, default flags) while a bystander client sends a
10-pose ``Blend`` every 5 ms and a health check goes out every 100 ms (both from a process of
their own, as another client's would be); one table.

    .venv/bin/python -m tests.bench.bench_bystander                 # ~2 min
    .venv/bin/python -m tests.bench.bench_bystander --seconds 5     # longer rows
    .venv/bin/python -m tests.bench.bench_bystander --only fuse     # rows whose name has it

A row: the heavy request sent by two client threads back to back for ``--seconds`` (at least two
calls each, so that both workers are busy), its status and median time; the bystander's Blend
latency (p50, p99, max) and the slowest health answer over that time; the server's resident
memory before the row, at its peak (sampled every 10 ms) and 2 s after the row. Targets (issue
18): bystander p99 <= 100 ms, health <= 1 s, memory back at its baseline.

Then the attack rows (``tests/bench/attacks.py``, one process each, ``--attack-seconds`` long,
beside the ordinary traffic it meets, on a server started as the attack needs: default flags,
``--live`` with ``--token-file``, ``--record`` on a small tmpfs) with a bystander Blend every
20 ms: its latency during the attack, the slowest health answer, the server's memory before, at
its peak, and when it came back within 20 % of before after the attack ended (looked at every
0.1 s for 10 s), the machine's load average, and what the server did with the attack and the
ordinary traffic (flagged where it is not what the attack expects). Targets (issue 36):
bystander p99 <= 100 ms and max <= 250 ms, memory back within 20 % within 10 s.
"""
from __future__ import annotations

import argparse
import contextlib
import multiprocessing as mp
import os
import sys
import tempfile
import threading
import time
from collections import Counter

import grpc
import numpy as np
from grpc_health.v1 import health_pb2, health_pb2_grpc

from dqpose import dq, lie, limits, trajectory
from dqpose.rpc import (
    BATCH_POSE_FACTOR,
    DEFAULT_MAX_MESSAGE_BYTES,
    DEFAULT_MAX_POSES,
    fusion_convert,
    geometry,
    handeye_convert,
    trajectories_convert,
    wire,
)
from dqpose.rpc._proto.dqpose.v1 import blending_pb2 as bpb
from dqpose.rpc._proto.dqpose.v1 import blending_pb2_grpc as bpb_grpc
from dqpose.rpc._proto.dqpose.v1 import fusion_pb2 as fpb
from dqpose.rpc._proto.dqpose.v1 import fusion_pb2_grpc as fpb_grpc
from dqpose.rpc._proto.dqpose.v1 import handeye_pb2_grpc as hpb_grpc
from dqpose.rpc._proto.dqpose.v1 import trajectories_pb2 as tpb
from dqpose.rpc._proto.dqpose.v1 import trajectories_pb2_grpc as tpb_grpc
from tests import _handeye as H
from tests.bench.attacks import (
    ATTACKS,
    FED,
    Served,
    Unavailable,
    default_server,
    run,
    said,
    served,
    surprises,
)
from tests.bench.bench_grpc import ServerProcess, request10

L = limits.DEFAULT
BIG = [("grpc.max_receive_message_length", 64 << 20), ("grpc.max_send_message_length", 64 << 20)]


# ---- the heavy requests: name -> (what it is, a function of a channel making one call)

def _fuse_request(n, outliers=0, times=False, **options):
    rng = np.random.default_rng(n)
    X = lie.se3_exp(rng.normal(size=6))
    Z = dq.mul(X, lie.se3_exp(0.01 * rng.normal(size=(n, 6))))
    Z[:outliers] = dq.mul(Z[:outliers], lie.se3_exp(np.tile([2.0, 0, 0, 0.3, 0, 0], (outliers, 1))))
    S = np.broadcast_to(np.eye(6) * 1e-4, (n, 6, 6))
    return fpb.FuseRequest(
        measurements=fusion_convert.measurement_msgs(Z, S,
                                              times=np.linspace(0, 0.1, n) if times else None),
        options=fusion_convert.options_msg(**options))


def _fuse(request):
    return lambda ch: fpb_grpc.FusionStub(ch).Fuse(request, timeout=600)


def _stream(requests):
    return lambda ch: list(fpb_grpc.FusionStub(ch).StreamFuse(iter(requests), timeout=600))


def _measurement(t, body="b"):
    return fpb.Measurement(body=body, source="s", time=t,
                           pose=geometry.dq_to_pose(np.array([1.0, 0, 0, 0, 0, 0, 0, 0])))


def _tick_flood():
    """Two measurements a body's max_time_jump apart in a window that holds both, at the
    largest output rate: ~60,000 ticks due at once, max_fused_per_request answers them."""
    first = fpb.FuseStreamRequest(output_rate=L.max_output_rate,
                                  measurements=[_measurement(0.0)])
    first.options.window = 2 * L.max_time_jump
    return [first, fpb.FuseStreamRequest(measurements=[_measurement(0.999 * L.max_time_jump)])]


def _window_flood(robust):
    """The probe's 50,000 measurements of one body in one window (50 messages of 1,000)."""
    first = fpb.FuseStreamRequest()
    first.options.window = 1e4
    first.options.robust = robust
    return [first] + [fpb.FuseStreamRequest(measurements=[
        _measurement(1e-3 * (1000 * k + j)) for j in range(1000)]) for k in range(50)]


def _calibrate(n, squares=None, corners=False):
    s = H.scene(n, seed=1)
    cs = None
    if squares:
        cs = H.exact_corners(s, squares)
    elif corners:
        cs = H.corners(s)
    request = handeye_convert.calibrate_msg(s.base_flange, s.camera_target, s.setup, corners=cs)
    return lambda ch: hpb_grpc.HandEyeStub(ch).Calibrate(request, timeout=600)


def _path(n, seed=0):
    t = np.linspace(0.0, n / 100.0, n)
    rng = np.random.default_rng(seed)
    xi = np.column_stack([np.outer(0.1 * np.sin(t), np.ones(3)),
                          np.outer(0.2 * np.cos(t), np.ones(3))])
    return t, lie.se3_exp(xi + 1e-4 * rng.normal(size=(n, 6)))


LIMITS = trajectory.Limits(max_linear_velocity=0.5, max_angular_velocity=1.0,
                           max_linear_acceleration=2.0, max_angular_acceleration=4.0)


def _plan():
    """max_poses waypoints at the rate that makes the most samples a plan may stream."""
    _, poses = _path(DEFAULT_MAX_POSES)
    duration = trajectory.plan([trajectory.Waypoint(p) for p in poses], LIMITS).duration
    rate = min(10_000.0, 0.99 * 10 * DEFAULT_MAX_POSES / duration)
    request = trajectories_convert.plan_msg(poses, LIMITS, rate)
    return lambda ch: list(tpb_grpc.TrajectoriesStub(ch).Plan(request, timeout=600))


def _smooth():
    t, poses = _path(DEFAULT_MAX_POSES)
    request = tpb.SmoothRequest(poses=geometry.stamped_msgs(t, poses),
                                limits=trajectories_convert.limits_msg(LIMITS), smoothing=1.0,
                                rate_hz=100.0)
    return lambda ch: tpb_grpc.TrajectoriesStub(ch).Smooth(request, timeout=600)


def _blend_batch():
    """As many 10-pose requests as one message of max_message_bytes holds (~57,000 poses; the
    batch's own limit, 100,000, is beyond it)."""
    rng = np.random.default_rng(0)
    n = min(BATCH_POSE_FACTOR * DEFAULT_MAX_POSES, DEFAULT_MAX_MESSAGE_BYTES // 73) // 10
    q = rng.normal(size=(n * 10, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    buf, _ = wire.blend_batch_items_wire(q, rng.normal(size=(n * 10, 3)), np.full(n, 10),
                                            np.empty(0), np.zeros(n, np.int64))
    data = buf.tobytes()
    call = None

    def run(ch):
        nonlocal call
        call = call or ch.unary_unary("/dqpose.v1.Blending/BlendBatch")
        return call(data, timeout=600)
    return run


def _blend_dib():
    """max_poses random poses, DIB to 1e-300 (never reached) for the most iterations allowed."""
    rng = np.random.default_rng(0)
    q = rng.normal(size=(DEFAULT_MAX_POSES, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    request = bpb.BlendRequest(poses=geometry.pose_msgs(q, rng.normal(size=(DEFAULT_MAX_POSES, 3))),
                               tolerance=1e-300, max_iterations=1000)
    return lambda ch: bpb_grpc.BlendingStub(ch).Blend(request, timeout=600)


def _interpolate():
    t, poses = _path(DEFAULT_MAX_POSES)
    request = bpb.InterpolateRequest(keyframes=geometry.stamped_msgs(t, poses),
                                     times=np.linspace(0, t[-1], DEFAULT_MAX_POSES).tolist())
    return lambda ch: bpb_grpc.BlendingStub(ch).Interpolate(request, timeout=600)


def cases() -> dict:
    """name -> (description, call maker); made lazily, the requests are large."""
    return {
        "probe: robust Fuse, 3,000": lambda: _fuse(_fuse_request(3000, 1000, robust=True)),
        "probe: robust Fuse, 10,000": lambda: _fuse(_fuse_request(10_000, robust=True)),
        "probe: Calibrate, 1,000 pairs": lambda: _calibrate(1000),
        "probe: Calibrate, 10,000 pairs": lambda: _calibrate(10_000),
        "probe: StreamFuse time=1e300": lambda: _stream([
            fpb.FuseStreamRequest(output_rate=10.0, measurements=[_measurement(0.0)]),
            fpb.FuseStreamRequest(measurements=[_measurement(1e300)])]),
        "probe: StreamFuse output_rate=1e8": lambda: _stream([
            fpb.FuseStreamRequest(output_rate=1e8, measurements=[_measurement(0.0)]),
            fpb.FuseStreamRequest(measurements=[_measurement(0.01 * k) for k in range(1, 3)])]),
        "probe: StreamFuse 50k window": lambda: _stream(_window_flood(False)),
        "probe: StreamFuse 50k window, robust": lambda: _stream(_window_flood(True)),
        f"Fuse robust, max_robust {L.max_robust}": lambda: _fuse(
            _fuse_request(L.max_robust, L.max_robust // 3, robust=True)),
        f"Fuse robust + acceleration_psd, max_correlated {L.max_correlated}": lambda: _fuse(
            _fuse_request(L.max_correlated, L.max_correlated // 5, times=True, robust=True,
                          acceleration_psd=np.eye(6) * 1e-3)),
        f"Fuse in time, max_poses {DEFAULT_MAX_POSES}": lambda: _fuse(
            _fuse_request(DEFAULT_MAX_POSES, times=True)),
        "StreamFuse ticks, max_fused_per_request": lambda: _stream(_tick_flood()),
        f"Calibrate, max_pairs {L.max_pairs} with corners": lambda: _calibrate(
            L.max_pairs, corners=True),
        f"Calibrate, max_corners {L.max_corners}": lambda: _calibrate(
            L.max_corners // 99, squares=(12, 10)),
        f"Plan, {DEFAULT_MAX_POSES} waypoints, {10 * DEFAULT_MAX_POSES} samples": _plan,
        f"Smooth, {DEFAULT_MAX_POSES} poses": _smooth,
        "BlendBatch, one full message of 10-pose requests": _blend_batch,
        f"Blend DIB, {DEFAULT_MAX_POSES} poses x 1000 iterations": _blend_dib,
        f"Interpolate, {DEFAULT_MAX_POSES} keyframes and times": _interpolate,
    }


# ---- the measurement

class Sampler(threading.Thread):
    """Calls ``fn`` every ``period`` s until stopped; keeps what it returns."""

    def __init__(self, fn, period: float):
        super().__init__(daemon=True)
        self.fn, self.period, self.values = fn, period, []
        self.stop = threading.Event()

    def run(self):
        while not self.stop.is_set():
            t0 = time.perf_counter()
            self.values.append(self.fn())
            self.stop.wait(max(0.0, self.period - (time.perf_counter() - t0)))


def timed(fn):
    def run():
        t0 = time.perf_counter()
        try:
            fn()
        except grpc.RpcError:
            return float("inf")
        return time.perf_counter() - t0
    return run


def _bystander(served: Served, stop, out, period: float = 0.005) -> None:
    """The bystander and the health checks, in a process of their own (as another client of the
    server would be): the heavy calls' answers, parsed in the bench's process, must not hold
    the bystander's interpreter lock and show up as server latency. Sends both lists of
    latencies (s) on ``out`` once ``stop`` is set. Health asks for no token, Blend sends the
    server's."""
    by = grpc.insecure_channel(served.target)
    blend = bpb_grpc.BlendingStub(by).Blend
    req = request10()
    health = health_pb2_grpc.HealthStub(by).Check

    def check():
        health(health_pb2.HealthCheckRequest(), timeout=5.0)

    def bystander():
        blend(req, timeout=5.0, metadata=served.metadata)

    samplers = [Sampler(timed(bystander), period), Sampler(timed(check), 0.1)]
    for s in samplers:
        s.start()
    out.send("started")
    stop.wait()
    for s in samplers:
        s.stop.set()
        s.join()
    out.send([s.values for s in samplers])
    by.close()


def row(server, name: str, make, seconds: float) -> dict:
    call = make()
    ch = grpc.insecure_channel(server.target, options=BIG)
    ctx = mp.get_context("spawn")
    stop, (got, out) = ctx.Event(), ctx.Pipe(duplex=False)
    others = ctx.Process(target=_bystander, args=(Served(server.target), stop, out),
                         daemon=True)
    others.start()
    assert got.recv() == "started"
    time.sleep(1.0)
    before = server.rss_mb()
    rss = Sampler(server.rss_mb, 0.01)
    rss.start()
    durations, codes = [], []

    def heavy():
        end = time.perf_counter() + seconds
        k = 0
        while k < 2 or time.perf_counter() < end:
            t0 = time.perf_counter()
            try:
                call(ch)
                codes.append("OK")
            except grpc.RpcError as e:
                codes.append(e.code().name)
            durations.append(time.perf_counter() - t0)
            k += 1

    workers = [threading.Thread(target=heavy) for _ in range(2)]
    for w in workers:
        w.start()
    for w in workers:
        w.join()
    stop.set()
    blends, checks = got.recv()
    others.join()
    rss.stop.set()
    rss.join()
    time.sleep(2.0)
    after = server.rss_mb()
    ch.close()
    lat = np.array(blends) * 1e3
    return dict(name=name, code="/".join(sorted(set(codes))), calls=len(durations),
                call_s=float(np.median(durations)), p50=float(np.percentile(lat, 50)),
                p99=float(np.percentile(lat, 99)), max=float(lat.max()),
                health=float(max(checks)) * 1e3, before=before,
                peak=max(rss.values), after=after)


#: the attack rows' bystander: a Blend every this many seconds (issue 36's)
ATTACK_PERIOD = 0.02
#: RSS back within this fraction above its baseline, looked at for this many seconds
BACK_WITHIN, BACK_SECONDS = 0.2, 10.0


def attack_row(server, served: Served, name: str, attack, seconds: float) -> dict:
    """The bystander (a Blend every :data:`ATTACK_PERIOD`) and health while ``attack`` runs in
    its own process for ``seconds``; the server's RSS then until it is back within
    :data:`BACK_WITHIN` of where it was. Its background traffic runs from ``warmup`` s before.
    What the attack and the background got from the server (``outcome``, ``fed``)."""
    ctx = mp.get_context("spawn")
    quiet, (fed, fed_out) = ctx.Event(), ctx.Pipe(duplex=False)
    background = None
    if attack.background is not None:
        background = ctx.Process(target=run, args=(attack.background, served, quiet, fed_out,
                                                   {}), daemon=True)
        background.start()
        time.sleep(attack.warmup)
    try:
        r = _attacked(server, served, name, attack.attack, seconds)
    finally:
        quiet.set()
        if background is not None:
            background.join(30)
    r["fed"] = fed.recv() if background is not None and fed.poll(5) else None
    return r


def _attacked(server, served: Served, name: str, attack, seconds: float) -> dict:
    ctx = mp.get_context("spawn")
    stop, (got, out) = ctx.Event(), ctx.Pipe(duplex=False)
    others = ctx.Process(target=_bystander, args=(served, stop, out, ATTACK_PERIOD), daemon=True)
    others.start()
    assert got.recv() == "started"
    time.sleep(1.0)
    before, load = server.rss_mb(), os.getloadavg()[0]
    rss = Sampler(server.rss_mb, 0.01)
    waits = Sampler(lambda: run_delays(server.proc.pid), 0.01)
    rss.start()
    waits.start()
    ended, (outcome, said_out) = ctx.Event(), ctx.Pipe(duplex=False)
    attacker = ctx.Process(target=run, args=(attack, served, ended, said_out, {}), daemon=True)
    attacker.start()
    time.sleep(seconds)
    ended.set()
    stop.set()
    blends, checks = got.recv()
    others.join()
    attacker.join(30)
    if attacker.is_alive():
        attacker.kill()
    for sampler in (rss, waits):
        sampler.stop.set()
        sampler.join()
    t0, back = time.perf_counter(), None
    while time.perf_counter() - t0 < BACK_SECONDS:
        if server.rss_mb() <= (1 + BACK_WITHIN) * before:
            back = time.perf_counter() - t0
            break
        time.sleep(0.1)
    lat = np.array(blends) * 1e3
    return dict(name=name, p50=float(np.percentile(lat, 50)), p99=float(np.percentile(lat, 99)),
                max=float(lat.max()), health=float(max(checks)) * 1e3, before=before,
                peak=max(rss.values), after=server.rss_mb(), back=back,
                load=(load, os.getloadavg()[0]), wait=worst_wait(waits.values),
                outcome=outcome.recv() if outcome.poll(5) else Counter({"no outcome": 1}))


def run_delays(pid: int) -> tuple:
    """``(start, end, {thread: ns})``: each thread of process ``pid``, the ns it has waited for
    a CPU while runnable, read between ``start`` and ``end`` (perf_counter s)."""
    out, start = {}, time.perf_counter()
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            with open(f"/proc/{pid}/task/{tid}/schedstat") as f:
                out[tid] = int(f.read().split()[1])
        except (OSError, IndexError):
            pass        # ended meanwhile
    return start, time.perf_counter(), out


#: the span in which the attack rows look for the server's longest wait for a CPU, s
WAIT_SPAN = 0.25


def worst_wait(samples: list) -> float:
    """The longest any thread waited for a CPU within :data:`WAIT_SPAN`, ms, from
    :func:`run_delays` samples (two read within the span from the first's start to the
    second's end): a server descheduled that long cannot answer in less, whatever its code
    does."""
    worst, j = 0, 0
    for i, (start, _, d) in enumerate(samples):
        j = max(i, j)
        while j + 1 < len(samples) and samples[j + 1][1] - start <= WAIT_SPAN:
            j += 1
        worst = max([worst] + [samples[j][2].get(tid, n) - n for tid, n in d.items()])
    return worst / 1e6


def verdict(r: dict, attack) -> str:
    """What the server did with the attack (and the background beside it), and what of it was
    not as :data:`~tests.bench.attacks.ATTACKS` expects."""
    wrong = surprises(r["outcome"], attack.expected, attack.allowed)
    text = said(r["outcome"]) or "-"
    if r["fed"] is not None:
        wrong += [f"fed world: {w}" for w in surprises(r["fed"], FED)]
        text += f"; the fed world: {said(r['fed'])}"
    return text + (f" **NOT AS EXPECTED: {'; '.join(wrong)}**" if wrong else "")


def attack_table(rows: list) -> None:
    print(f"\nAttacks ({ATTACK_PERIOD * 1e3:.0f} ms bystander; RSS back: seconds after the "
          f"attack until within {BACK_WITHIN:.0%} of before, looked at for {BACK_SECONDS:g} s)"
          f"\n")
    print(f"| attack | bystander Blend p50 / p99 / max ms | health max ms | RSS before / peak / "
          f"now MB | RSS back | load before / after | CPU wait ms (a server thread's longest in "
          f"{WAIT_SPAN * 1e3:.0f} ms) | what the server did |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        if "skipped" in r:
            print(f"| {r['name']} | | | | | | | not run: {r['skipped']} |")
            continue
        back = "no" if r["back"] is None else f"{r['back']:.1f} s"
        print(f"| {r['name']} | {r['p50']:.1f} / {r['p99']:.1f} / {r['max']:.1f} | "
              f"{r['health']:.0f} | {r['before']:.0f} / {r['peak']:.0f} / {r['after']:.0f} | "
              f"{back} | {r['load'][0]:.1f} / {r['load'][1]:.1f} | {r['wait']:.0f} | "
              f"{r['verdict']} |")


def attack_rows(only: str, seconds: float, default) -> list:
    """The attack rows whose name has ``only``, each on a server of its setup: ``default``
    (the bench's, default flags) or one started for the rows of another setup in turn."""
    rows: list = []
    chosen = {name: a for name, a in ATTACKS.items() if only.lower() in name.lower()}
    for setup in dict.fromkeys(a.setup for a in chosen.values()):
        names = [name for name, a in chosen.items() if a.setup is setup]
        with tempfile.TemporaryDirectory() as tmp, contextlib.ExitStack() as stack:
            try:
                flags = stack.enter_context(setup(tmp))
            except Unavailable as e:
                rows += [dict(name=name, skipped=str(e)) for name in names]
                continue
            server = default
            if setup is not default_server:
                server = ServerProcess("aio", quiet_log=True, extra=flags.flags)
                stack.callback(server.stop)
            target = served(server.target, server.events, flags)
            for name in names:
                rows.append(attack_row(server, target, name, chosen[name], seconds))
                r = rows[-1]
                r["verdict"] = verdict(r, chosen[name])
                print(f"  {name}: p99 {r['p99']:.1f} ms, max {r['max']:.1f} ms, RSS "
                      f"{r['before']:.0f}/{r['peak']:.0f}/{r['after']:.0f} MB, back "
                      f"{r['back']}, CPU wait {r['wait']:.0f} ms; {r['verdict']}",
                      file=sys.stderr, flush=True)
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=2.0, help="heavy calls per row, at least")
    ap.add_argument("--only", default="", help="rows whose name contains this")
    ap.add_argument("--attack-seconds", type=float, default=10.0, help="each attack's length")
    ap.add_argument("--attacks", action="store_true", help="the attack rows only")
    args = ap.parse_args(argv)
    server = ServerProcess("aio", quiet_log=True)
    rows: list = []
    try:
        baseline = server.rss_mb()
        attacked = attack_rows(args.only, args.attack_seconds, server)
        for name, make in cases().items():
            if not args.attacks and args.only.lower() in name.lower():
                rows.append(row(server, name, make, args.seconds))
                r = rows[-1]
                print(f"  {name}: {r['code']} x{r['calls']}, p99 {r['p99']:.1f} ms, health "
                      f"{r['health']:.0f} ms, RSS {r['before']:.0f}/{r['peak']:.0f}/"
                      f"{r['after']:.0f} MB", file=sys.stderr, flush=True)
    finally:
        server.stop()
    print(f"\nServer RSS at start {baseline:.0f} MB; workers {L.workers}; limits "
          f"{service_limits()}")
    attack_table(attacked)
    if not rows:
        return 0
    print("\n| request | status x calls | call s (median) | bystander Blend p50 / p99 / max ms "
          "| health max ms | RSS before / peak / after MB |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['name']} | {r['code']} x{r['calls']} | {r['call_s']:.3f} | "
              f"{r['p50']:.1f} / {r['p99']:.1f} / {r['max']:.1f} | {r['health']:.0f} | "
              f"{r['before']:.0f} / {r['peak']:.0f} / {r['after']:.0f} |")
    return 0


def service_limits() -> str:
    return ", ".join(f"{k} {v:g}" for k, v in vars(L).items() if k != "workers")


if __name__ == "__main__":
    sys.exit(main())
