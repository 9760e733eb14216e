"""Benchmarks of the dual-quaternion core: `make bench` (= `python -m tests.bench.bench_core`).

Prints one table. For each operation it times, in one run on the same inputs:

* our C core called directly from C (``harness.c`` compiled here with gcc against
  ``service/csrc/dq.c`` and ``blend.c``, the flags of ``setup.py``);
* the floor: the same math as a plain scalar C loop (``floor.c``: atan2/sqrt/sin/cos per pose,
  nothing precomputed), compiled in the same run;
* our Python API (``dqpose.dq``);
* the Python-level peers pytransform3d and scipy.

Times are medians of repeated samples after a warm-up. Ratios are to *ours at the same level*
(C rows to the C core, Python rows to our Python API). ``dev`` is the largest absolute
difference of a component from our result (``q`` and ``-q`` counted equal), so a peer that does
different math (scipy: slerp + lerp, chordal rotation mean) shows it there. The row "C core ÷
C floor" (issue 10's target for independent ScLERP pairs) is the median of ratios of samples of
the two taken alternately, so it holds still when other jobs load the machine; the rows "ours
Python ÷ C floor" (issue 38's target for ScLERP pairs from Python) likewise alternate the call
from Python with the floor's loop, built as a shared library and called through ctypes.

Options: ``--plot PATH`` also saves ns/pose versus batch size (PNG); ``--quick`` uses fewer
samples (for a smoke run, not for quoting).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import time
import timeit
from pathlib import Path

import numpy as np

from dqpose import dq
from tests.bench._table import markdown

ROOT = Path(__file__).resolve().parents[2]
HERE = Path(__file__).resolve().parent
BUILD = HERE / "_build"
CSRC = ROOT / "service" / "csrc"
# The flags of setup.py, so the harness times the code the extension runs.
CFLAGS = ["-O3", "-std=c99", "-Wall", "-Wextra", "-Wno-unused-parameter", "-fno-math-errno"]

N_TAU = 10_000       # ScLERP: one pair, this many tau
N_PAIRS = 10_000     # ScLERP: this many independent pairs
N_BATCH = 100_000    # the from-Python batch
N_CONV = 1_000       # conversions

SAMPLES = 15


# ---- inputs ------------------------------------------------------------------------------

def _rotvec_quat(rv):
    """Rotation vectors (..., 3) to unit quaternions (..., 4), scalar first."""
    rv = np.asarray(rv, dtype=float)
    ang = np.linalg.norm(rv, axis=-1, keepdims=True)
    half = 0.5 * ang
    with np.errstate(invalid="ignore", divide="ignore"):
        k = np.where(ang > 0, np.sin(half) / np.where(ang > 0, ang, 1), 0.5)
    return np.concatenate([np.cos(half), k * rv], axis=-1)


def _random_poses(rng, n, rot_scale, trans_scale):
    rv = rng.normal(size=(n, 3)) * rot_scale
    return dq.from_pose(_rotvec_quat(rv), rng.normal(size=(n, 3)) * trans_scale)


def make_inputs(rng):
    """Realistic sizes: trajectory segments of up to ~2 rad and ~0.5 m; pose sets scattered by
    ~0.1 rad and ~5 cm around their mean (fusion of noisy measurements)."""
    a = _random_poses(rng, 1, 1.0, 0.5)[0]
    b = dq.mul(a, dq.from_pose(_rotvec_quat([0.9, -0.6, 1.1]), [0.3, 0.1, -0.2]))
    pa = _random_poses(rng, N_BATCH, 1.0, 0.5)
    pb = dq.mul(pa, _random_poses(rng, N_BATCH, 0.7, 0.3))
    # Same hemisphere: pytransform3d does not flip, so the comparison stays the same math.
    pb *= np.where(np.sum(pa[:, :4] * pb[:, :4], axis=1) < 0, -1.0, 1.0)[:, None]
    mean = _random_poses(rng, 1, 1.0, 0.5)[0]
    sets = {m: dq.mul(mean, _random_poses(rng, m, 0.1, 0.05)) for m in (10, 1000)}
    return {
        "pair": np.concatenate([a, b]),
        "taus": np.linspace(0.0, 1.0, N_TAU),
        "taus_batch": np.linspace(0.0, 1.0, N_BATCH),
        "pairs_a": pa[:N_PAIRS], "pairs_b": pb[:N_PAIRS],
        "pairs_tau": rng.uniform(size=N_PAIRS),
        "batch_a": pa, "batch_b": pb, "batch_tau": rng.uniform(size=N_BATCH),
        "set10": sets[10], "set1000": sets[1000],
        "conv_dq": _random_poses(rng, N_CONV, 1.0, 0.5),
    }


# ---- C side ------------------------------------------------------------------------------

def build_harness() -> Path:
    cc = shutil.which(os.environ.get("CC", "gcc"))
    if cc is None:
        sys.exit("bench: a C compiler (gcc) is needed to build the C harness")
    BUILD.mkdir(exist_ok=True)
    exe = BUILD / "harness"
    cmd = [cc, *CFLAGS, f"-I{CSRC}", str(HERE / "harness.c"), str(HERE / "floor.c"),
           str(CSRC / "dq.c"), str(CSRC / "blend.c"), "-lm", "-o", str(exe)]
    subprocess.run(cmd, check=True)
    return exe


def build_floor() -> Path:
    """``floor.c`` as a shared library, for the plain C loop timed beside calls from Python."""
    cc = shutil.which(os.environ.get("CC", "gcc")) or "gcc"
    BUILD.mkdir(exist_ok=True)
    lib = BUILD / "libfloor.so"
    subprocess.run([cc, *CFLAGS, "-shared", "-fPIC", str(HERE / "floor.c"), "-lm", "-o",
                    str(lib)], check=True)
    return lib


def python_over_floor(a, b, tau, samples: int) -> float:
    """The median over ``samples`` of (``dq.sclerp(a, b, tau)`` from Python) / (the plain C loop
    ``floor_sclerp_each`` over the same pairs), the two timed alternately as the harness's
    ratios are, so a change of load moves both sides of each ratio alike."""
    import ctypes
    floor = ctypes.CDLL(str(build_floor())).floor_sclerp_each
    out = np.empty_like(a)
    ptr = ctypes.POINTER(ctypes.c_double)
    args = [x.ctypes.data_as(ptr) for x in (a, b, tau)] + [ctypes.c_size_t(len(tau)),
                                                          out.ctypes.data_as(ptr)]
    ratios = []
    for k in range(samples + 1):
        t0 = time.perf_counter()
        dq.sclerp(a, b, tau)
        t1 = time.perf_counter()
        floor(*args)
        t2 = time.perf_counter()
        if k:                   # the first pair warms both up
            ratios.append((t1 - t0) / (t2 - t1))
    return float(np.median(ratios))


def run_harness(exe: Path, inp: dict) -> tuple[dict, dict]:
    data = BUILD / "data"
    data.mkdir(exist_ok=True)
    for name in ("pair", "taus", "pairs_a", "pairs_b", "pairs_tau", "set10", "set1000",
                 "conv_dq"):
        np.ascontiguousarray(inp[name], dtype=np.float64).tofile(data / f"{name}.bin")
    proc = subprocess.run([str(exe), str(data)], check=True, capture_output=True, text=True)
    times = {}
    for line in proc.stdout.splitlines():
        r = json.loads(line)
        times[(r["op"], r["impl"])] = r
    outs = {p.stem: np.fromfile(p) for p in data.glob("*.out")}
    return times, outs


# ---- Python side -------------------------------------------------------------------------

def median_call(fn, samples=None) -> float:
    """Median seconds per call of fn() over samples of >= 20 ms each, after a warm-up."""
    t = timeit.Timer(fn)
    number, _ = t.autorange()                       # warm-up and calibration (>= 0.2 s)
    number = max(1, number // 10)
    s = t.repeat(repeat=samples or SAMPLES, number=number)
    return float(np.median(s)) / number


def dev(x, ref) -> float:
    """Largest component difference, q and -q equal (per pose)."""
    x = np.asarray(x, dtype=float).reshape(-1, 8)
    ref = np.asarray(ref, dtype=float).reshape(-1, 8)
    return float(np.max(np.minimum(np.abs(x - ref).max(axis=1), np.abs(x + ref).max(axis=1))))


def _pt3d():
    try:
        import pytransform3d.trajectories as ptr
        import pytransform3d.transformations as pt
        import pytransform3d.uncertainty as pu
        return pt, ptr, pu
    except ImportError:
        return None


def _scipy_R():
    try:
        from scipy.spatial.transform import Rotation, Slerp
        return Rotation, Slerp
    except ImportError:
        return None


def _dq_from_R_t(R, t):
    q = R.as_quat(scalar_first=True)
    return dq.from_pose(q, t)


def scipy_sclerp_tau(Rotation, Slerp, a, b, taus):
    """Rotation by slerp, translation linearly: the usual decoupled interpolation."""
    qa, ta = dq.to_pose(a)
    qb, tb = dq.to_pose(b)
    s = Slerp([0.0, 1.0], Rotation.from_quat(np.stack([qa, qb]), scalar_first=True))
    return s(taus), (1.0 - taus)[:, None] * ta + taus[:, None] * tb


def scipy_sclerp_pairs(Rotation, qa, ta, qb, tb, taus):
    Ra = Rotation.from_quat(qa, scalar_first=True)
    Rb = Rotation.from_quat(qb, scalar_first=True)
    rel = (Ra.inv() * Rb).as_rotvec()
    R = Ra * Rotation.from_rotvec(taus[:, None] * rel)
    return R, (1.0 - taus)[:, None] * ta + taus[:, None] * tb


def scipy_mean(Rotation, q, t):
    return Rotation.from_quat(q, scalar_first=True).mean(), t.mean(axis=0)


# ---- the table ---------------------------------------------------------------------------

class Row:
    def __init__(self, op, impl, seconds, per=1, unit="call", ours=None, dev_=None,
                 target=None, note=""):
        self.op, self.impl, self.seconds, self.per, self.unit = op, impl, seconds, per, unit
        self.ours, self.dev, self.target, self.note = ours, dev_, target, note

    @property
    def value(self):
        return self.seconds / self.per

    def cells(self):
        ratio = "1" if self.ours is None else f"{self.value / self.ours.value:.2f}"
        tgt, ok = "", ""
        if self.target is not None:
            limit, what = self.target
            val = self.value if what == "per" else self.seconds
            tgt = f"≤ {fmt_time(limit)}" + ("" if what == "per" else " total")
            ok = "PASS" if val <= limit else "FAIL"
        d = "—" if self.dev is None else f"{self.dev:.1e}"
        return [self.op, self.impl + (f" ({self.note})" if self.note else ""), fmt_time(self.value),
                self.unit, ratio, d, tgt, ok]


class RatioRow:
    """A ratio of two times measured in the same run, against a target ratio."""

    def __init__(self, op, impl, ratio: float, limit: float):
        self.op, self.impl, self.ratio, self.limit = op, impl, ratio, limit

    def cells(self):
        return [self.op, self.impl, f"{self.ratio:.2f}×", "ratio", "—", "—", f"≤ {self.limit:.2f}×",
                "PASS" if self.ratio <= self.limit else "FAIL"]


def fmt_time(s):
    if s is None:
        return "—"
    if s < 1e-6:
        return f"{s * 1e9:.1f} ns"
    if s < 1e-3:
        return f"{s * 1e6:.2f} µs"
    return f"{s * 1e3:.2f} ms"


def render(rows) -> str:
    head = ["operation", "implementation", "median", "per", "× ours", "max dev vs ours",
            "target", "pass"]
    return markdown(head, [r.cells() for r in rows])



class _Run:
    """One run's inputs, the C harness's times (``ct``) and outputs (``co``), the peers found
    (pytransform3d, scipy; None when absent) and the rows measured so far."""

    def __init__(self, inp: dict, ct: dict, co: dict):
        self.inp, self.ct, self.co = inp, ct, co
        self.pt3, self.sp = _pt3d(), _scipy_R()
        self.rows: list = []

    def crow(self, op, impl, label, per_unit, ref_out, out_name, core_row=None, target=None,
             note=""):
        """The C harness's row of ``op`` by ``impl`` (core or floor), deviation from ``ref_out``."""
        r = self.ct[(op, impl)]
        row = Row(label, "C core" if impl == "core" else "C floor (scalar, libm per pose)",
                  r["seconds"], r["units"] if per_unit else 1, per_unit or "call", core_row,
                  dev(self.co[out_name], ref_out) if out_name in self.co else None, target, note)
        self.rows.append(row)
        return row


def sclerp_rows(run: "_Run") -> None:
    """ScLERP in the C core and from Python: one pair at many tau, independent pairs."""
    inp, pt3, sp = run.inp, run.pt3, run.sp
    a, b = inp["pair"][:8], inp["pair"][8:]
    pt, ptr, pu = pt3 or (None, None, None)
    Rotation, Slerp = sp or (None, None)
    ct = run.ct
    taus = inp["taus"]
    pa, pb, ptau = inp["pairs_a"], inp["pairs_b"], inp["pairs_tau"]
    # -- ScLERP, one pair, many tau
    label = f"ScLERP 1 pair × {N_TAU} tau"
    ours = dq.sclerp(a, b, taus)
    core = run.crow("sclerp_tau", "core", label, "pose", ours, "sclerp_tau_core",
                    target=(25e-9, "per"))
    run.crow("sclerp_tau", "floor", label, "pose", ours, "sclerp_tau_floor", core)
    py = Row(label, "ours Python", median_call(lambda: dq.sclerp(a, b, taus)), N_TAU, "pose")
    run.rows.append(py)
    if pt3:
        pt, ptr, pu = pt3
        A, B = np.broadcast_to(a, (N_TAU, 8)), np.broadcast_to(b, (N_TAU, 8))
        run.rows.append(Row(label, "pytransform3d", median_call(
            lambda: ptr.dual_quaternions_sclerp(A, B, taus)), N_TAU, "pose", py,
            dev(ptr.dual_quaternions_sclerp(A, B, taus), ours)))
    if sp:
        Rotation, Slerp = sp
        R, t = scipy_sclerp_tau(Rotation, Slerp, a, b, taus)
        run.rows.append(Row(label, "scipy", median_call(
            lambda: scipy_sclerp_tau(Rotation, Slerp, a, b, taus)), N_TAU, "pose", py,
            dev(_dq_from_R_t(R, t), ours), note="Slerp + lerp"))

    # -- ScLERP, independent pairs
    label = f"ScLERP {N_PAIRS} pairs"
    ours = dq.sclerp(pa, pb, ptau)
    core = run.crow("sclerp_pairs", "core", label, "pair", ours, "sclerp_pairs_core",
                    target=(60e-9, "per"))
    run.crow("sclerp_pairs", "floor", label, "pair", ours, "sclerp_pairs_floor", core)
    # Issue 10: vectorised across poses, the kernel is to cost at most 0.6 of the scalar loop.
    # The harness times the two alternately for this ratio, so a load change hits both alike.
    run.rows.append(RatioRow(label, "C core ÷ C floor (ratio to the scalar C loop)",
                             ct[("sclerp_pairs", "core/floor")]["ratio"], 0.6))
    py = Row(label, "ours Python", median_call(lambda: dq.sclerp(pa, pb, ptau)), N_PAIRS, "pair")
    run.rows.append(py)
    # Issue 38: the whole call from Python (checks, the output's allocation) at most 0.5 of it.
    run.rows.append(RatioRow(label, "ours Python ÷ C floor (alternating)",
                             python_over_floor(pa, pb, ptau, 201), 0.5))
    if pt3:
        run.rows.append(Row(label, "pytransform3d", median_call(
            lambda: ptr.dual_quaternions_sclerp(pa, pb, ptau)), N_PAIRS, "pair", py,
            dev(ptr.dual_quaternions_sclerp(pa, pb, ptau), ours)))
    if sp:
        qa, ta = dq.to_pose(pa)
        qb, tb = dq.to_pose(pb)
        R, t = scipy_sclerp_pairs(Rotation, qa, ta, qb, tb, ptau)
        run.rows.append(Row(label, "scipy", median_call(
            lambda: scipy_sclerp_pairs(Rotation, qa, ta, qb, tb, ptau)), N_PAIRS, "pair", py,
            dev(_dq_from_R_t(R, t), ours), note="slerp + lerp"))



def sclerp_call_rows(run: "_Run") -> None:
    """ScLERP from Python: one call, and 100k samples of one pair or of 100k pairs."""
    inp, pt3, sp = run.inp, run.pt3, run.sp
    a, b = inp["pair"][:8], inp["pair"][8:]
    pt, ptr, pu = pt3 or (None, None, None)
    Rotation, Slerp = sp or (None, None)
    # -- ScLERP from Python: one call
    label = "ScLERP 1 call"
    ours = dq.sclerp(a, b, 0.3)
    py = Row(label, "ours Python", median_call(lambda: dq.sclerp(a, b, 0.3)),
             target=(1e-6, "total"))
    run.rows.append(py)
    if pt3:
        run.rows.append(Row(label, "pytransform3d", median_call(
            lambda: pt.dual_quaternion_sclerp(a, b, 0.3)), ours=py,
            dev_=dev(pt.dual_quaternion_sclerp(a, b, 0.3), ours)))
    if sp:
        run.rows.append(Row(label, "scipy", median_call(
            lambda: scipy_sclerp_tau(Rotation, Slerp, a, b, np.array([0.3]))), ours=py,
            dev_=dev(_dq_from_R_t(*scipy_sclerp_tau(Rotation, Slerp, a, b, np.array([0.3]))),
                     ours), note="Slerp + lerp"))

    # -- 100k batch from Python
    tb_ = inp["taus_batch"]
    ba, bb, bt = inp["batch_a"], inp["batch_b"], inp["batch_tau"]
    label = f"ScLERP {N_BATCH // 1000}k batch, 1 pair"
    ours = dq.sclerp(a, b, tb_)
    py = Row(label, "ours Python", median_call(lambda: dq.sclerp(a, b, tb_)),
             target=(5e-3, "total"))
    run.rows.append(py)
    if pt3:
        A, B = np.broadcast_to(a, (N_BATCH, 8)), np.broadcast_to(b, (N_BATCH, 8))
        run.rows.append(Row(label, "pytransform3d", median_call(
            lambda: ptr.dual_quaternions_sclerp(A, B, tb_), 5), ours=py,
            dev_=dev(ptr.dual_quaternions_sclerp(A, B, tb_), ours)))
    label = f"ScLERP {N_BATCH // 1000}k batch, pairs"
    ours = dq.sclerp(ba, bb, bt)
    # No target: the 100k batch is samples of one interpolation (the row above); here
    # every pair is its own screw, and the kernel's own 60 ns per pair is its target.
    py = Row(label, "ours Python", median_call(lambda: dq.sclerp(ba, bb, bt)))
    run.rows.append(py)
    run.rows.append(RatioRow(label, "ours Python ÷ C floor (alternating)",
                             python_over_floor(ba, bb, bt, 51), 0.5))
    if pt3:
        run.rows.append(Row(label, "pytransform3d", median_call(
            lambda: ptr.dual_quaternions_sclerp(ba, bb, bt), 5), ours=py,
            dev_=dev(ptr.dual_quaternions_sclerp(ba, bb, bt), ours)))


def mean_rows(run: "_Run") -> None:
    """DLB and DIB over 10 and 1000 poses."""
    inp, pt3, sp = run.inp, run.pt3, run.sp
    pt, ptr, pu = pt3 or (None, None, None)
    Rotation, Slerp = sp or (None, None)
    ct, co = run.ct, run.co
    # -- means
    for m in (10, 1000):
        q = inp[f"set{m}"]
        label = f"DLB n={m}"
        ours = dq.dlb(q)
        core = run.crow(f"dlb{m}", "core", label, None, ours, f"dlb{m}",
                        target=(50e-9, "total") if m == 10 else None)
        run.crow(f"dlb{m}", "floor", label, None, ours, "-", core)
        run.rows.append(Row(label, "ours Python", median_call(lambda: dq.dlb(q))))

        res = dq.dib(q, return_info=True)
        ours = res.mean
        it = int(res.iterations)
        label = f"DIB n={m} ({it} steps, {it + 1} passes)"
        r = ct[(f"dib{m}", "core")]
        # A pass is one log-sum over all poses; DIB takes `steps` steps and `steps + 1` passes.
        passes = r["iters"] + 1
        core = Row(label, "C core", r["seconds"], m * passes, "pose·pass",
                   dev_=dev(co[f"dib{m}_core"], ours), target=(20e-9, "per"))
        run.rows.append(core)
        if m == 1000:
            run.rows.append(Row(label, "C core", r["seconds"], 1, "call",
                                dev_=dev(co[f"dib{m}_core"], ours), target=(125e-6, "total")))
        rf = ct[(f"dib{m}", "floor")]
        run.rows.append(Row(label, "C floor (scalar, libm per pose)", rf["seconds"],
                            m * (rf["iters"] + 1), "pose·pass", core,
                            dev(co[f"dib{m}_floor"], ours)))
        py = Row(label, "ours Python", median_call(lambda: dq.dib(q)),
                 target=(3e-6, "total") if m == 10 else None)
        run.rows.append(py)
        if pt3:
            Ts = dq.to_matrix(q)
            Tm, _ = pu.estimate_gaussian_transform_from_samples(Ts)
            run.rows.append(Row(label, "pytransform3d", median_call(
                lambda: pu.estimate_gaussian_transform_from_samples(Ts), 7), ours=py,
                dev_=dev(dq.from_matrix(Tm), ours), note="Fréchet mean, 20 fixed steps"))
        if sp:
            qq, tt = dq.to_pose(q)
            R, t = scipy_mean(Rotation, qq, tt)
            run.rows.append(Row(label, "scipy", median_call(lambda: scipy_mean(Rotation, qq, tt)),
                                ours=py, dev_=dev(_dq_from_R_t(R, t), ours),
                                note="Rotation.mean + mean t"))


def conversion_rows(run: "_Run") -> None:
    """to_matrix and from_matrix."""
    inp, pt3, sp = run.inp, run.pt3, run.sp
    pt, ptr, pu = pt3 or (None, None, None)
    Rotation, Slerp = sp or (None, None)
    ct = run.ct
    # -- conversions
    cq = inp["conv_dq"]
    Ts = dq.to_matrix(cq)
    for op, fn, arg, ref, ptf in (
            ("to_matrix", dq.to_matrix, cq, Ts, "transforms_from_dual_quaternions"),
            ("from_matrix", dq.from_matrix, Ts, cq, "dual_quaternions_from_transforms")):
        label = f"{op} ×{N_CONV}"
        r = ct[(op, "core")]
        run.rows.append(Row(label, "C core", r["seconds"], N_CONV, "pose"))
        py = Row(label, "ours Python", median_call(lambda: fn(arg)), N_CONV, "pose")
        run.rows.append(py)
        if pt3:
            f = getattr(ptr, ptf)
            got = f(arg)
            d = (np.abs(got - ref).max() if op == "to_matrix" else dev(got, ref))
            run.rows.append(Row(label, "pytransform3d", median_call(lambda: f(arg)), N_CONV, "pose",
                                py, float(d)))


def main(argv=None):
    global SAMPLES
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--plot", metavar="PATH", help="also save ns/pose vs batch size as a PNG")
    ap.add_argument("--quick", action="store_true", help="fewer samples (smoke run)")
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args(argv)
    if args.quick:
        SAMPLES = 5

    rng = np.random.default_rng(args.seed)
    inp = make_inputs(rng)
    run = _Run(inp, *run_harness(build_harness(), inp))
    for rows in (sclerp_rows, sclerp_call_rows, mean_rows, conversion_rows):
        rows(run)
    print(f"dqpose benchmarks — {platform.processor() or platform.machine()}, "
          f"{os.cpu_count()} CPUs, load {os.getloadavg()[0]:.2f}, Python "
          f"{platform.python_version()}, NumPy {np.__version__}; medians of {SAMPLES} samples")
    print(render(run.rows))

    if args.plot:
        plot(args.plot, inp["pair"][:8], inp["pair"][8:], run.pt3, run.sp)


def plot(path, a, b, pt3, sp):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sizes = [1, 10, 100, 1_000, 10_000, 100_000]
    rng = np.random.default_rng(7)
    series = {"dqpose (ours)": [], "pytransform3d": [], "scipy slerp+lerp": []}
    for n in sizes:
        pa = _random_poses(rng, n, 1.0, 0.5)
        pb = dq.mul(pa, _random_poses(rng, n, 0.7, 0.3))
        pb *= np.where(np.sum(pa[:, :4] * pb[:, :4], axis=1) < 0, -1.0, 1.0)[:, None]
        t = rng.uniform(size=n)
        k = 5 if n >= 10_000 else SAMPLES
        series["dqpose (ours)"].append(median_call(lambda: dq.sclerp(pa, pb, t), k) / n)
        if pt3:
            series["pytransform3d"].append(
                median_call(lambda: pt3[1].dual_quaternions_sclerp(pa, pb, t), k) / n)
        if sp:
            qa, ta = dq.to_pose(pa)
            qb, tb = dq.to_pose(pb)
            series["scipy slerp+lerp"].append(
                median_call(lambda: scipy_sclerp_pairs(sp[0], qa, ta, qb, tb, t), k) / n)
    fig, ax = plt.subplots(figsize=(6, 4))
    for name, ys in series.items():
        if ys:
            ax.loglog(sizes, np.array(ys) * 1e9, "o-", label=name)
    ax.set_xlabel("batch size (independent pairs)")
    ax.set_ylabel("ns per interpolated pose")
    ax.set_title("ScLERP from Python, one core")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    print(f"plot saved to {path}")


if __name__ == "__main__":
    main()
