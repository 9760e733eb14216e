"""The constant-twist fit a tick runs, alone: ``python -m tests.bench.bench_fit``.

The fits are those of bench_engine's tick scene (:class:`tests.bench.bench_engine.TickScene`:
static bodies seen by 4 cameras at 50 Hz, window 0.2 s, so 41 measurements a fit, 4 Gauss-Newton
iterations), captured from the ticks a round of the scene answers (``_dqcore.motion_fit``'s
arguments, as ``dqpose.fusion.motion`` calls it). Each is timed

* in C: ``dq_motion_run`` (service/csrc/motion.c) called from ``motion_harness.c``, compiled here
  with setup.py's flags, with the leave-one-out NIS (as a tick asks) and without;
* through the binding ``_dqcore.motion_fit``, one fit a call, with and without the NIS.

Times are the median pass over all fits (and the best pass) of the thread's CPU time; the
harness's poses, covariances and NIS are checked to be the binding's bit for bit. Options:
``--fits N`` (default 200), ``--samples N`` (default 15), ``--against DIR`` (repeatable): also
the harness built from another tree's csrc (``git archive <commit> service/csrc | tar -x -C
DIR``), the trees alternated batch by batch, for a before and after in one run.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from dqpose import _dqcore
from dqpose.fusion import motion
from tests.bench import bench_engine as be
from tests.bench._table import markdown
from tests.bench.bench_core import BUILD, CFLAGS, CSRC, HERE

# (motion_rows.c and motion_nis.c were motion.c's until it was split: a tree without them has
# their functions in motion.c)
SOURCES = ("motion.c", "motion_rows.c", "motion_nis.c", "gn.c", "fusion.c", "linalg6.c", "se3.c",
           "dq.c", "blend.c")


def tick_fits(fits: int = 200, seed: int = 0) -> list[tuple]:
    """The first ``fits`` constant-twist fits of the tick scene's ticks (1 s of history, then the
    ticks each request makes due), as ``_dqcore.motion_fit``'s arguments: each tick answered by
    the Python path (``World.tick``), which makes that call with the arguments the C tick
    (``World.tick_wire``) gives ``dq_motion_run``."""
    calls: list[tuple] = []
    fit = motion._c.motion_fit

    def kept(*args):
        if len(calls) < fits:
            calls.append(tuple(np.array(a) if isinstance(a, np.ndarray) else a for a in args))
        return fit(*args)

    scene = be.TickScene(100, seed)
    eng, i = be._filled(scene, 1.0)
    motion._c = _Wrapped(kept)
    try:
        while len(calls) < fits:
            for body, t in eng.due(eng.ingest(scene.wire(i))):
                eng.world.tick(body, t)
            i += 1
    finally:
        motion._c = _dqcore
    return calls


class _Wrapped:
    """``_dqcore`` with its ``motion_fit`` replaced."""

    def __init__(self, motion_fit):
        self.motion_fit = motion_fit

    def __getattr__(self, name):
        return getattr(_dqcore, name)


def binding(calls: list[tuple], samples: int, nis: bool) -> tuple[float, float]:
    """Median and best pass's CPU seconds a fit through ``_dqcore.motion_fit``."""
    calls = calls if nis else [c[:11] + (None,) + c[12:] for c in calls]
    times = []
    for _ in range(samples + 1):
        t0 = time.thread_time()
        for c in calls:
            _dqcore.motion_fit(*c)
        times.append((time.thread_time() - t0) / len(calls))
    times = sorted(times[1:])
    return times[len(times) // 2], times[0]


def harness(calls: list[tuple], samples: int, csrc=CSRC) -> dict:
    """The C harness's rows by ``nis`` (median, best seconds a fit) built from ``csrc``, after
    checking its results against the binding's bit for bit."""
    cc = shutil.which("gcc")
    if cc is None:
        sys.exit("bench: a C compiler (gcc) is needed to build the C harness")
    n = len(calls[0][0])
    if any(len(c[0]) != n or c[2] is not None and not c[2].all() or c[3] is not None
           or len(c[7]) or not c[9] or c[10] is not None or c[11] is not True for c in calls):
        sys.exit("bench: the harness takes fits of one size, all inliers, no latency estimated, "
                 "a twist without prior, tested=True")
    BUILD.mkdir(exist_ok=True)
    tag = "" if csrc == CSRC else "_" + str(abs(hash(str(csrc))))
    exe, data = BUILD / f"motion_harness{tag}", BUILD / "motion_data"
    data.mkdir(exist_ok=True)
    sources = [str(Path(csrc) / f) for f in SOURCES if (Path(csrc) / f).exists()]
    subprocess.run([cc, *CFLAGS, f"-I{csrc}", str(HERE / "motion_harness.c"), *sources, "-lm",
                    "-o", str(exe)], check=True)
    for k, name in ((0, "poses"), (1, "covariances"), (4, "stamps"), (5, "latencies")):
        np.array([c[k] for c in calls], dtype=float).tofile(data / f"{name}.bin")
    out = subprocess.run([str(exe), str(data), str(len(calls)), str(n), str(samples)],
                         check=True, capture_output=True, text=True).stdout
    rows = {r["nis"]: r for r in map(json.loads, out.splitlines())}
    got = [np.fromfile(data / f"{name}.out") for name in ("mean", "P", "nis")]
    fitted = [_dqcore.motion_fit(*c) for c in calls]
    want = [np.concatenate([np.ravel(r[j]) for r in fitted]) for j in (0, 13, 11)]
    for name, a, b in zip(("pose", "covariance", "NIS"), got, want):
        if a.tobytes() != b.tobytes():
            sys.exit(f"bench: the harness's {name} is not the binding's bit for bit")
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--fits", type=int, default=200)
    ap.add_argument("--samples", type=int, default=15)
    ap.add_argument("--against", type=Path, action="append", default=[],
                    help="another tree's service/csrc (repeatable)")
    args = ap.parse_args(argv)
    calls = tick_fits(args.fits)
    iters = [int(_dqcore.motion_fit(*c)[6]) for c in calls]
    trees = [("", CSRC)] + [(f" ({d})", d) for d in args.against]
    runs: dict = {name: [] for name, _ in trees}
    for _ in range(3):      # alternated batches
        for name, csrc in trees:
            runs[name].append(harness(calls, max(1, args.samples // 3), csrc))
    rows = []
    for name, _ in trees:
        for nis in (1, 0):
            med = float(np.median([r[nis]["median"] for r in runs[name]]))
            best = min(r[nis]["best"] for r in runs[name])
            rows.append([f"C dq_motion_run{' with NIS' if nis else ''}{name}",
                         f"{med * 1e6:.1f} µs", f"{best * 1e6:.1f} µs"])
    for nis in (True, False):
        med, best = binding(calls, args.samples, nis)
        rows.append([f"_dqcore.motion_fit{' with NIS' if nis else ''}",
                     f"{med * 1e6:.1f} µs", f"{best * 1e6:.1f} µs"])
    print(f"bench_fit: {len(calls)} fits of the tick scene, {len(calls[0][0])} measurements, "
          f"{np.median(iters):.0f} iterations (median); load {os.getloadavg()[0]:.1f}")
    print(markdown(["fit", "a fit (median pass)", "best pass"], rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
