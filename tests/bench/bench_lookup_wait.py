"""A Lookup that waits (``LookupRequest.wait``): ``python -m tests.bench.bench_lookup_wait``.

In process, as the server runs it: the World servicer's Lookup (``dqpose.rpc.world_wait``) on an
event loop, its fits in the servicer's worker pool; the Publish requests from their bytes in
another thread (``World.publish_bytes``, as a Publish call's pool job). Each of ``--waits``
Lookups asks for a body 0.2 s past its newest measurement (beyond ``max_extrapolation``) with
``wait`` 10 s; once it waits (its first try failed, its slot held), one Publish request brings
the measurement at that time. Timed: from just before that request's step to the Lookup's
answer on the event loop (wall time: the step, the hub's listener, the loop's wake-up, the
retry's fit in the pool), p50 and p99, and the load average of the run.
"""
from __future__ import annotations

import argparse
import asyncio
import os
import threading
import time

import numpy as np

from dqpose import dq, lie
from tests.bench._table import markdown

RATE, AHEAD = 30.0, 0.2


class _Context:
    """What the Lookup handler reads of a gRPC call's context: its peer and metadata."""

    @staticmethod
    def peer() -> str:
        return "ipv4:127.0.0.1:50000"

    @staticmethod
    def invocation_metadata() -> tuple:
        return ()


def _request(t: float, seq: int) -> bytes:
    from dqpose.rpc._proto.dqpose.v1 import world_pb2 as wpb
    from dqpose.rpc.fusion_convert import measurement_msgs
    pose = dq.mul(lie.se3_exp(np.array([0.0, 0.0, 0.0, 0.1, 0.0, 0.0]) * t),
                  lie.se3_exp(np.full(6, 1e-4)))
    cov = np.diag([1e-4] * 3 + [1e-6] * 3)[None]
    return wpb.PublishRequest(measurements=measurement_msgs(
        pose[None], cov, names=["cam"], bodies=["box"], times=np.array([t])), producer="p",
        sequence=seq).SerializeToString()


async def _waits(n: int) -> np.ndarray:
    from dqpose.rpc._proto.dqpose.v1 import world_pb2 as wpb
    from dqpose.rpc.world import World
    server = World()
    hub = server.hub("", make=True)
    t, seq = 0.0, 0
    for _ in range(int(RATE)):          # a second of history at 30 Hz
        seq += 1
        server.publish_bytes(hub, _request(t, seq), seq, "")
        t += 1.0 / RATE
    newest = t - 1.0 / RATE
    out = np.empty(n)
    for k in range(n):
        at = newest + AHEAD
        data = _request(at, seq + 1)
        seq += 1
        lookup = asyncio.ensure_future(server._lookup(
            wpb.LookupRequest(source="box", time=at, wait=10.0), _Context()))
        while not server.waits.count:           # waiting: its first try failed
            await asyncio.sleep(0)
            assert not lookup.done(), lookup.result()
        started = []

        def publish(data=data, seq=seq):
            started.append(time.perf_counter())
            server.publish_bytes(hub, data, seq, "")

        threading.Thread(target=publish).start()
        await lookup
        out[k] = time.perf_counter() - started[0]
        newest = at
    server.calls.close()
    return out


def rows(waits: int = 300) -> list[list[str]]:
    load0 = os.getloadavg()[0]
    dt = asyncio.run(_waits(waits)) * 1e3
    load = 0.5 * (load0 + os.getloadavg()[0])
    detail = (f"{waits} waits, 1 body at {RATE:g} Hz, each Lookup {AHEAD:g} s past the newest; "
              f"load {load:.1f}")
    return [["Publish → waiting Lookup answered", f"{np.percentile(dt, 50):.3f}",
             f"{np.percentile(dt, 99):.3f}", "ms", detail]]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--waits", type=int, default=300, help="waiting Lookups (default: 300)")
    args = ap.parse_args(argv)
    print(markdown(["what", "p50", "p99", "unit", "conditions"], rows(args.waits)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
