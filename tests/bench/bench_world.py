"""The shared world (``dqpose.world``): one table.

    .venv/bin/python -m tests.bench.bench_world            # ~1 min
    .venv/bin/python -m tests.bench.bench_world --trials 500 --lookups 2000

Sections (each a function returning rows of the one table, so that more can be added):

* :func:`lookup_rows` — ``World.relative`` (Lookup's server time, in process): the latency of a
  lookup between two moving bodies, each seen at 30 Hz by two cameras with latencies over a 1 s
  window (60 measurements a body's fit, the constant-twist fit over time), p50/p99 over
  ``--lookups`` calls: bodies that share no uncertain extrinsic (two fits composed), and bodies
  seen by the same camera with an ``extrinsic_covariance`` (the joint fit with its error), and
  ``World.pose`` alone. Target: ≤ 200 µs.
* :func:`nees_rows` — the mean NEES of ``World.relative`` against the truth over ``--trials``
  draws, on the scene of tests/test_world.py: one camera whose mount is uncertain (1° / 5 mm)
  sees both bodies twice (0.1° / 0.5 mm each); beside it the composition of the two bodies'
  marginals, which ignores the error they share. 6 is consistent; the 95 % band of the mean of
  500 χ²₆ draws is about 6 ± 0.3.
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from dqpose import dq, lie
from dqpose.fusion import Measurement, Source
from dqpose.world import World, WorldOptions
from tests.bench._table import markdown

HEAD = ["section", "case", "value", "unit", "detail"]
COV = np.diag(np.r_[np.full(3, np.deg2rad(0.3)), np.full(3, 1e-3)] ** 2)
MOUNT = np.diag(np.r_[np.full(3, np.deg2rad(1.0)), np.full(3, 5e-3)] ** 2)


def _moving_world(shared: bool, seed: int = 0):
    """Bodies "a" and "b" on screws, each seen at 30 Hz by two cameras over 2 s (window 1 s):
    with ``shared`` camera "top" (extrinsic uncertain) sees both, else each body has its own
    pair of exact cameras. Returns the world and a function that publishes the next 30 Hz
    tick."""
    rng = np.random.default_rng(seed)
    names = ["top", "side"] if shared else ["a1", "a2", "b1", "b2"]
    sources = [Source(n, lie.se3_exp(rng.normal(size=6) * 0.5), latency=0.02 + 0.01 * k,
                      extrinsic_covariance=MOUNT if n == "top" else None)
               for k, n in enumerate(names)]
    world = World(sources=sources, options=WorldOptions(window=1.0, buffer=10.0))
    seen = {"a": names[:2], "b": names[:2]} if shared else {"a": names[:2], "b": names[2:]}
    X0 = {b: lie.se3_exp(rng.normal(size=6) * 0.3) for b in "ab"}
    V = {b: rng.normal(size=6) * 0.2 for b in "ab"}
    by = {s.name: s for s in sources}
    tick = [0]

    def more():
        t = tick[0] / 30.0
        tick[0] += 1
        batch = []
        for b in "ab":
            for n in seen[b]:
                s = by[n]
                X = dq.mul(X0[b], lie.se3_exp((t - s.latency) * V[b]))
                z = dq.mul(dq.mul(dq.conj(s.extrinsic), X),
                           lie.se3_exp(rng.multivariate_normal(np.zeros(6), COV)))
                batch.append(Measurement(n, b, t, z, COV))
        world.publish(batch)

    for _ in range(60):
        more()
    return world, more


def _timed(call, n: int, before=None) -> np.ndarray:
    """``call``'s duration (µs) ``n`` times, ``before`` run untimed ahead of each."""
    call()
    out = np.empty(n)
    for i in range(n):
        if before is not None:
            before()
        t0 = time.perf_counter()
        call()
        out[i] = time.perf_counter() - t0
    return out * 1e6


def lookup_rows(lookups: int = 1000) -> list[list[str]]:
    """Per case: a call after a new 30 Hz tick of measurements (the fits run) and a call
    repeated without new data (the answer the world keeps)."""
    rows = []
    for shared in (False, True):
        world, more = _moving_world(shared)
        n = len(world.pose("a").fused.inliers)
        cases = [("pose", "pose of a body" + (", seen by the uncertain camera" if shared else ""),
                  lambda: world.pose("a")),
                 ("relative", "relative, " + ("one camera with extrinsic_covariance sees both"
                                              if shared else "no shared uncertain extrinsic"),
                  lambda: world.relative("a", "b"))]
        for _, label, call in cases:
            for fresh in (True, False):
                us = _timed(call, lookups, more if fresh else None)
                rows.append(["Lookup (in process)",
                             label + ("; after new data" if fresh else "; repeated"),
                             f"{np.percentile(us, 50):.1f}", "µs p50",
                             f"p99 {np.percentile(us, 99):.1f} µs; {n} measurements a body, "
                             f"{lookups} calls"])
    return rows


def _nees(trials: int, seed: int = 0) -> tuple[float, float]:
    from tests.test_world import relative_nees
    return relative_nees(trials, seed)


def nees_rows(trials: int = 500) -> list[list[str]]:
    joint, composed = _nees(trials)
    scene = "one camera (mount 1° / 5 mm) sees both bodies"
    return [["NEES of relative", "World.relative (joint fit)", f"{joint:.2f}", "mean NEES",
             f"{scene}; {trials} trials; 6 expected"],
            ["NEES of relative", "composition of the marginals", f"{composed:.2f}", "mean NEES",
             f"{scene}; {trials} trials; ignores the shared error"]]


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=500)
    ap.add_argument("--lookups", type=int, default=1000)
    args = ap.parse_args(argv)
    print(markdown(HEAD, lookup_rows(args.lookups) + nees_rows(args.trials)))


if __name__ == "__main__":
    main()
