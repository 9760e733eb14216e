"""Benchmark of the fusion core: ``python -m tests.bench.bench_fusion_core``.

Prints one table: the maximum-likelihood fusion of 10 measurements with full (anisotropic,
correlated) covariances per call, on the same problems (the scenes of tests/fusion/_scenes.py), by

* our C core ``dq_fuse`` called from C (``fusion_harness.c`` compiled here with the flags of
  setup.py), without and with the leave-one-out NIS;
* the binding ``_dqcore.fuse``, one problem per call and a batch of all problems in one call;
* ``dqpose.fusion.fuse`` (validation, frames, consistency report: the whole Python API);
* GTSAM from Python: ``PriorFactorPose3`` per measurement, Levenberg–Marquardt and
  ``Marginals``, with its default parameters and with tight ones (relative and absolute error
  tolerance 1e-16, as tests/fusion/test_static.py uses before it finishes with Gauss–Newton steps).

A second table: the time-aligned estimate (constant twist, one latency estimated, one
configured; the scenes of tests/csrc/test_fusion.py) of 20 and 90 measurements by the C kernel
``_dqcore.motion_fit`` (fit, information and leave-one-out NIS), the NumPy reference
(tests/fusion_reference.py, the block-diagonal fit the service ran before the kernel) and
``dqpose.fusion.fuse(..., times=...)`` end to end.

Times are medians of repeated samples after a warm-up (the C rows: the median pass over all
problems, and the best pass). ``max dev`` is the largest over the problems of
``|Log(ours⁻¹ theirs)|`` (rad/m) and of the covariance difference relative to its largest entry.

Options: ``--problems N`` (default 300), ``--quick`` (fewer samples, for a smoke run),
``--motion-only`` (the second table only).
"""
from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import timeit

import numpy as np

from dqpose import _dqcore, dq, fusion, lie
from dqpose.fusion.motion import determined_without_each, motion_start
from tests.bench._table import markdown
from tests.bench.bench_core import BUILD, CFLAGS, CSRC, HERE, fmt_time

N = 10


def problems(count: int, seed: int = 7):
    from tests.fusion._scenes import measure, random_cov, random_pose
    rng = np.random.default_rng(seed)
    S = np.array([[random_cov(rng) for _ in range(N)] for _ in range(count)])
    Z = np.array([measure(rng, random_pose(rng), s) for s in S])
    return Z, S


def per_call(fn, samples: int) -> float:
    """Median seconds per call of fn() over samples of >= ~20 ms each, after a warm-up."""
    t = timeit.Timer(fn)
    number, _ = t.autorange()
    number = max(1, number // 10)
    return float(np.median(t.repeat(repeat=samples, number=number))) / number


def c_core(Z, S, samples: int):
    cc = shutil.which("gcc")
    if cc is None:
        sys.exit("bench: a C compiler (gcc) is needed to build the C harness")
    BUILD.mkdir(exist_ok=True)
    exe, data = BUILD / "fusion_harness", BUILD / "fusion_data"
    data.mkdir(exist_ok=True)
    subprocess.run([cc, *CFLAGS, f"-I{CSRC}", str(HERE / "fusion_harness.c"),
                    *(str(CSRC / f) for f in ("fusion.c", "linalg6.c", "se3.c", "dq.c", "blend.c")),
                    "-lm", "-o", str(exe)], check=True)
    Z.tofile(data / "poses.bin")
    S.tofile(data / "covariances.bin")
    out = subprocess.run([str(exe), str(data), str(len(Z)), str(N), str(samples)], check=True,
                         capture_output=True, text=True).stdout
    rows = {r["nis"]: r for r in map(json.loads, out.splitlines())}
    mean = np.fromfile(data / "mean.out").reshape(-1, 8)
    cov = np.fromfile(data / "covariance.out").reshape(-1, 6, 6)
    return rows, mean, cov


def gtsam_fuse(gtsam, Z, S, params):
    from tests._gtsam import priors

    graph, values = priors(Z, S)
    result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    return result.atPose3(0).matrix(), gtsam.Marginals(graph, result).marginalCovariance(0)


def deviation(mean, cov, ref_mean, ref_cov):
    """(pose, covariance) deviation from ours, worst over the problems."""
    e = lie.se3_log(dq.mul(dq.conj(ref_mean), mean))
    c = np.abs(cov - ref_cov).max(axis=(1, 2)) / np.abs(ref_cov).max(axis=(1, 2))
    return float(np.abs(e).max()), float(c.max())


def motion_table(samples: int, count: int = 20):
    from tests import fusion_reference as ref
    from tests.csrc.test_fusion import motion_scene

    rng = np.random.default_rng(11)
    sources = [fusion.Source("a", latency=0.03, latency_sigma=0.01),
               fusion.Source("b", latency=0.005), fusion.Source("c")]
    rows = []
    for n in (20, 90):
        scenes = [motion_scene(rng, n, (True, False)) for _ in range(count)]
        args = []
        for Z, S, model in scenes:
            inlier = np.ones(n, bool)
            tested = ~inlier | determined_without_each(model, inlier)
            # the C fit picks its own start where there is a twist (None); the reference needs one
            args.append((Z, S, model, inlier, motion_start(Z, S, model, inlier), tested,
                         ref.motion_start(Z, model, inlier)))
        k = iter(range(10 ** 9))

        def kernel():
            Z, S, m, inlier, start, tested, _ = args[next(k) % count]
            return _dqcore.motion_fit(Z, S, inlier, start, m.stamp, m.latency, m.slot, m.prior,
                                      m.prior_w, m.twist, m.twist_w, tested)

        def numpy():
            Z, S, m, inlier, _, tested, start = args[next(k) % count]
            return ref.motion_fit(Z, S, m, inlier, start, tested)

        def api():
            Z, S, m, *_ = scenes[next(k) % count]
            names = ["abc"[i % 3] for i in range(n)]
            return fusion.fuse(Z, S, names=names, sources=sources, times=m.stamp, time=0.0)

        c = [kernel() for _ in range(count)]
        r = [numpy() for _ in range(count)]
        f = [api() for _ in range(count)]
        dev = max(float(np.abs(lie.se3_log(dq.mul(dq.conj(a.mean), b[0]))).max())
                  for a, b in zip(r, c))
        steps = np.mean([int(b[6]) for b in c])
        base = per_call(kernel, samples)
        rows.append((n, "C kernel _dqcore.motion_fit", base, base, f"{dev:.1e}",
                     f"{steps:.1f} Gauss-Newton steps, NIS included"))
        rows.append((n, "NumPy reference (tests/fusion_reference.py)",
                     per_call(numpy, max(3, samples // 3)), base, "—", "the pre-kernel path"))
        rows.append((n, "dqpose.fusion.fuse(..., times=...)", per_call(api, samples), base, "—",
                     f"validation, frames, report; {np.mean([x.iterations for x in f]):.1f} steps"))
    head = ["n", "implementation", "per estimate", "× C kernel", "max dev pose", "note"]
    lines = [[str(n), label, fmt_time(t), f"{t / b:.1f}", d, note]
             for n, label, t, b, d, note in rows]
    print("Time-aligned estimate (constant twist; pose, twist and one latency estimated, one "
          "configured), 20 scenes each; target: well under 0.2 ms from Python")
    print(markdown(head, lines))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--problems", type=int, default=300)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--motion-only", action="store_true")
    args = ap.parse_args(argv)
    samples = 5 if args.quick else 15
    if args.motion_only:
        return motion_table(samples)
    Z, S = problems(args.problems)
    P = len(Z)

    ours = [fusion.fuse(z, s) for z, s in zip(Z, S)]
    mean = np.array([f.mean for f in ours])
    cov = np.array([f.covariance for f in ours])
    iterations = np.mean([f.iterations for f in ours])
    rows = []

    c_rows, c_mean, c_cov = c_core(Z, S, samples)
    for nis, label in ((0, "C core dq_fuse, from C"), (1, "C core dq_fuse + NIS, from C")):
        r = c_rows[nis]
        rows.append((label, r["seconds"], f"best pass {fmt_time(r['best'])}",
                     deviation(c_mean, c_cov, mean, cov) if nis else None))

    k = iter(range(10 ** 9))
    one = lambda: _dqcore.fuse(Z[next(k) % P], S[next(k) % P], None)  # noqa: E731
    rows.append(("_dqcore.fuse, one problem per call", per_call(one, samples), "", None))
    batch = _dqcore.fuse(Z, S, None)
    rows.append((f"_dqcore.fuse, batch of {P} in one call",
                 per_call(lambda: _dqcore.fuse(Z, S, None), samples) / P, "per problem",
                 deviation(batch[0], batch[1], mean, cov)))
    rows.append(("dqpose.fusion.fuse", per_call(lambda: fusion.fuse(Z[next(k) % P],
                                                                     S[next(k) % P]), samples),
                 "validation, NIS, report", None))

    try:
        import gtsam
    except ImportError:
        gtsam = None
    if gtsam is not None:
        tight = gtsam.LevenbergMarquardtParams()
        tight.setRelativeErrorTol(1e-16)
        tight.setAbsoluteErrorTol(1e-16)
        tight.setMaxIterations(500)
        for params, label in ((gtsam.LevenbergMarquardtParams(), "default parameters"),
                              (tight, "error tolerances 1e-16")):
            res = [gtsam_fuse(gtsam, z, s, params) for z, s in zip(Z, S)]
            g_mean = dq.from_matrix(np.array([m for m, _ in res]))
            g_cov = np.array([c for _, c in res])
            t = per_call(lambda: gtsam_fuse(gtsam, Z[next(k) % P], S[next(k) % P], params),
                         max(3, samples // 3))
            rows.append(("GTSAM LM + marginals, from Python", t, label,
                         deviation(g_mean, g_cov, mean, cov)))

    base = rows[0][1]
    head = ["implementation", "per fusion", "× C core", "max dev pose", "max dev cov", "note"]
    lines = [[label, fmt_time(t), f"{t / base:.1f}",
              "—" if d is None else f"{d[0]:.1e}", "—" if d is None else f"{d[1]:.1e}", note]
             for label, t, note, d in rows]
    print(f"Fusion of {N} measurements with full covariances, {P} problems "
          f"(Gauss-Newton steps: {iterations:.2f} on average); target: C core <= 10 µs")
    print(markdown(head, lines))
    print()
    motion_table(samples)


if __name__ == "__main__":
    main()
