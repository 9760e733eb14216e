"""ListFrames (``World.ListFrames``) of a world of 1,000 frames: the server's CPU time a call.

    .venv/bin/python -m tests.bench.bench_frames            # ~10 s
    .venv/bin/python -m tests.bench.bench_frames --calls 2000

The world: 600 bodies measured at 30 Hz over 2 s by 4 sources, 200 static bodies seen once,
4 sources, 195 statics (on bodies and on each other) and the world: 1,000 frames. Timed is the
handler's work as the server's worker runs it (:func:`dqpose.rpc.world_frames.list_frames`: the
world's frames and their serialized ``FrameList``), by ``time.thread_time`` (CPU time of the
thread, which a loaded machine's other processes do not add to), per call over ``--calls``
calls: the world unchanged since the last call (each body's info kept), after a Publish request
that brought one body a measurement (its info made again), after one that brought every body
one (a live world: every body's span new at each call), and after a configuration (every
body's made again). Target: <= 1 ms a call.
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from dqpose import dq
from dqpose.frames import Static
from dqpose.fusion import Source
from dqpose.hub import Hub
from dqpose.rpc._proto.dqpose.v1 import world_pb2 as pb
from dqpose.rpc.world_convert import Encoder
from dqpose.rpc.world_frames import list_frames
from dqpose.world import WorldOptions
from tests.bench._table import markdown

BODIES, STATIC_BODIES, STATICS = 600, 200, 195
SOURCES = [Source(f"cam{k}") for k in range(4)]
ONE = np.array([1.0, 0, 0, 0, 0, 0, 0, 0])


def world() -> Hub:
    hub = Hub("", Encoder())
    statics = [Static(f"b{k}" if k % 2 else f"s{k - 1}" if k else "", f"s{k}",
                      dq.from_pose([1.0, 0, 0, 0], [0.1 * k, 0, 0])) for k in range(STATICS)]
    hub.configure(SOURCES, {}, WorldOptions(buffer=10.0), statics=statics,
                  static_bodies=[f"shelf{k}" for k in range(STATIC_BODIES)])
    times = np.arange(60) / 30.0
    n = BODIES * len(times)
    bodies = [f"b{k}" for k in range(BODIES)] * len(times)
    hub.world.ingest(bodies, [f"cam{k % 4}" for k in range(n)], np.repeat(times, BODIES),
                     np.tile(ONE, (n, 1)), np.tile(np.eye(6) * 1e-6, (n, 1, 1)))
    hub.world.ingest([f"shelf{k}" for k in range(STATIC_BODIES)], ["cam0"] * STATIC_BODIES,
                     np.full(STATIC_BODIES, 1.0), np.tile(ONE, (STATIC_BODIES, 1)),
                     np.tile(np.eye(6) * 1e-6, (STATIC_BODIES, 1, 1)))
    return hub


def per_call(hub: Hub, calls: int, before=None) -> float:
    """CPU seconds of the handler's work a call (``before`` each call, untimed)."""
    request = pb.ListFramesRequest()
    spent = 0.0
    for k in range(calls):
        if before is not None:
            before(k)
        t0 = time.thread_time()
        list_frames(hub, request)
        spent += time.thread_time() - t0
    return spent / calls


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--calls", type=int, default=500)
    args = p.parse_args()
    hub = world()
    frames = pb.FrameList.FromString(list_frames(hub, pb.ListFramesRequest())).frames
    assert len(frames) == 1 + BODIES + STATIC_BODIES + len(SOURCES) + STATICS == 1000

    def one_body(k: int) -> None:
        hub.world.ingest(["b0"], ["cam0"], np.array([2.0 + k / 1e4]), ONE[None],
                         np.eye(6)[None] * 1e-6)

    def every_body(k: int) -> None:
        n = BODIES
        hub.world.ingest([f"b{j}" for j in range(n)], [f"cam{j % 4}" for j in range(n)],
                         np.full(n, 3.0 + k / 30.0), np.tile(ONE, (n, 1)),
                         np.tile(np.eye(6) * 1e-6, (n, 1, 1)))

    def configured(_: int) -> None:
        w = hub.world
        w.configure(sources=w.sources, arms={}, options=w.options, statics=w.tree.statics,
                    static_bodies=w.tree.static_body_names)

    rows = [["unchanged", per_call(hub, args.calls)],
            ["after a request to one body", per_call(hub, args.calls, one_body)],
            ["after a request to every body (a live world: each call lists new spans)",
             per_call(hub, max(args.calls // 5, 5), every_body)],
            ["after a configuration", per_call(hub, max(args.calls // 10, 5), configured)]]
    print(markdown(["ListFrames, 1,000 frames", "server CPU / call (ms)"],
                   [[case, f"{1e3 * s:.3f}"] for case, s in rows]))


if __name__ == "__main__":
    main()
