"""Benchmark of path smoothing under limits: `.venv/bin/python -m tests.bench.bench_smoothing`.

Issue 10's case: 500 poses of a teleoperation-like path at 100 Hz (``teleop_path`` of
tests/smoothing/test_solve.py: at rest at both ends, sines of 0.2-0.7 Hz, 5-15 cm and 0.2-0.6 rad
per axis) with isotropic Gaussian noise of rms norm 1 mm and 0.5 deg, and limits equal to the true
path's own peak linear and angular velocity and acceleration, so the noisy samples break them by
far and the unconstrained smoothing by a little: the limits bind.

Rows, on the same trials (``--trials`` seeds), all at smoothing 1 (cutoff 2 Hz) where it applies:

* **ours**: ``dqpose.smoothing.smooth`` (banded start, then one PIQP QP per channel that needs
  one, through ``casadi.conic``; the returned samples measured and a broken limit tightened);
* **banded only**: the unconstrained banded solve that ours starts from;
* **OSQP**: ours with OSQP (casadi's plugin, its default tolerances 1e-3) in place of PIQP, one
  pass, the samples not re-measured: whether its "solved" is right;
* **IPOPT**: the nonlinear problem itself (exact increments ``Log(Rc_j-1^-1 Rc_j)``, exact
  residuals through the cumulative spline, the norm limits as ``|Q|^2 <= L^2``) built with
  casadi SX and solved by IPOPT from the same banded start; build time separately, on the first
  ``--ipopt-trials`` trials only (it takes seconds);
* **moving average** (21 samples) and **Savitzky-Golay** (31 samples, cubic): positions and
  sign-aligned quaternions (then normalised), no limits.

Time: median wall time of a call from Python (first call excluded: it loads casadi's plugins).
Errors: translation ``|t - t_true|`` (mm) and rotation angle of ``R_true^-1 R`` (deg), median
and max over every pose of every trial. Worst violation: the largest ``measured / limit - 1`` of
the four limits over the trials, measured from the samples by finite differences
(``dqpose.smoothing.peaks``); 0 means every limit held.
"""
from __future__ import annotations

import argparse
import os
import time

import numpy as np

from dqpose import dq
from dqpose.smoothing import peaks, smooth
from dqpose.smoothing.solve import evaluate, smooth_checked, unconstrained
from dqpose.smoothing.spline import rot_dq
from tests.smoothing.test_solve import errors, limits_from, noisy, teleop_path

FIELDS = ("linear_velocity", "angular_velocity", "linear_acceleration", "angular_acceleration")


def violation(times, poses, limits) -> float:
    pk = peaks(times, poses)
    return max(0.0, max(getattr(pk, f) / getattr(limits, "max_" + f) - 1 for f in FIELDS))


def _split(poses):
    q, p = dq.to_pose(poses)
    flip = np.cumsum(np.r_[0, np.einsum("ij,ij->i", q[1:], q[:-1]) < 0]) % 2
    return np.where(flip[:, None] == 1, -q, q), p


def ours(t, y, limits):
    return smooth(t, y, limits)


def banded(t, y, limits):
    q, p = dq.to_pose(y)
    prob, c, rc, _ = unconstrained(t, q, p, 1.0)
    return t, evaluate(prob, c, rc, t)


def osqp(t, y, limits):
    q, p = dq.to_pose(y)
    return smooth_checked(t, q, p, limits, 1.0, 0.0, solver=("osqp", {"verbose": False}),
                             verify=False)


def moving_average(t, y, limits, window=21):
    from scipy.ndimage import uniform_filter1d
    q, p = _split(y)
    f = lambda a: uniform_filter1d(a, window, axis=0, mode="nearest")  # noqa: E731
    qs = f(q)
    return t, dq.from_pose(qs / np.linalg.norm(qs, axis=1, keepdims=True), f(p))


def savitzky_golay(t, y, limits, window=31, order=3):
    from scipy.signal import savgol_filter
    q, p = _split(y)
    f = lambda a: savgol_filter(a, window, order, axis=0)  # noqa: E731
    qs = f(q)
    return t, dq.from_pose(qs / np.linalg.norm(qs, axis=1, keepdims=True), f(p))


# ---- IPOPT on the nonlinear problem -------------------------------------------------------------
class Ipopt:
    """The nonlinear problem of dqpose.smoothing with casadi SX, solved by IPOPT."""

    def __init__(self, t, y, limits):
        import casadi as ca

        t0 = time.perf_counter()
        q, p = dq.to_pose(y)
        prob, c0, rc0, r_meas = unconstrained(t, q, p, 1.0)
        self.prob, self.c0, self.rc0, self.t = prob, c0, rc0, t
        s, h, Z = prob.s, prob.s.h, prob.s.z
        zmap = np.clip(np.arange(s.m) - 2, 0, Z - 1)
        i, b = s.basis(t)
        cum = np.cumsum(b[:, ::-1], axis=1)[:, ::-1]
        w = prob.w
        # the samples' quaternions on the reference's side (the residual's Log takes the short way)
        ref_at = s.rotations(rc0, t)
        qm = r_meas[:, :4] * np.sign(np.einsum("ij,ij->i", r_meas[:, :4], ref_at[:, :4]))[:, None]

        xp, xe = ca.SX.sym("xp", Z, 3), ca.SX.sym("xe", Z, 3)
        unit_p = limits.max_linear_velocity * h
        unit_r = limits.max_angular_velocity * h
        cost = 0
        g, ubg = [], []

        # position: exact (linear), norm limits as squares
        c = ca.DM(c0) + unit_p * xp[zmap.tolist(), :]
        fit = sum(b[:, j:j + 1] * c[(i + j).tolist(), :] for j in range(4)) - ca.DM(p)
        cost += ca.sum1(ca.DM(w) * ca.sum2(fit ** 2)) / unit_p ** 2
        d = c[1:, :] - c[:-1, :]
        cost += prob.lam * ca.sumsqr(d[2:, :] - 2 * d[1:-1, :] + d[:-2, :]) / unit_p ** 2
        for Q, L in ((d / h, limits.max_linear_velocity),
                     ((d[1:, :] - d[:-1, :]) / h ** 2, limits.max_linear_acceleration)):
            g.append(ca.sum2(Q ** 2) / L ** 2)
            ubg.append(np.ones(Q.shape[0]))

        # orientation: control rotations Rc_j Exp(eps), exact increments and residuals
        rc = _qmul(_cols(rc0[:, :4]), _qexp(unit_r * xe[zmap.tolist(), :]))
        dd = _qlog(_qmul(_conj(_rows(rc, slice(0, s.m - 1))), _rows(rc, slice(1, s.m))))
        R = _rows(rc, i.tolist())
        for j in (1, 2, 3):
            R = _qmul(R, _qexp(ca.DM(cum[:, j:j + 1]) * dd[(i + j - 1).tolist(), :]))
        res = _qlog(_qmul(_conj(_cols(qm)), R))
        cost += ca.sum1(ca.DM(w) * ca.sum2(res ** 2)) / unit_r ** 2
        cost += prob.lam * ca.sumsqr(dd[2:, :] - 2 * dd[1:-1, :] + dd[:-2, :]) / unit_r ** 2
        for Q, L in ((dd / h, limits.max_angular_velocity),
                     ((dd[1:, :] - dd[:-1, :]) / h ** 2, limits.max_angular_acceleration)):
            g.append(ca.sum2(Q ** 2) / L ** 2)
            ubg.append(np.ones(Q.shape[0]))

        x = ca.veccat(xp, xe)
        self.solver = ca.nlpsol("smooth", "ipopt",
                                {"x": x, "f": cost / w.max(), "g": ca.vertcat(*g)},
                                {"print_time": False, "ipopt.print_level": 0, "ipopt.sb": "yes"})
        # the ends pinned at rest where the banded start puts them, as in ours
        lbx, ubx = np.full((Z, 3, 2), -np.inf), np.full((Z, 3, 2), np.inf)
        lbx[[0, -1]] = ubx[[0, -1]] = 0.0
        self.bounds = dict(lbx=lbx.ravel(order="F"), ubx=ubx.ravel(order="F"),
                           ubg=np.concatenate(ubg), lbg=-np.inf)
        self.units, self.Z = (unit_p, unit_r), Z
        self.build = time.perf_counter() - t0

    def solve(self):
        t0 = time.perf_counter()
        sol = self.solver(x0=np.zeros(6 * self.Z), **self.bounds)
        elapsed = time.perf_counter() - t0
        x = np.asarray(sol["x"]).ravel()
        xp, xe = x[:3 * self.Z].reshape(3, -1).T, x[3 * self.Z:].reshape(3, -1).T
        E = self.prob.s.E
        c = self.c0 + self.units[0] * (E @ xp)
        rc = dq.mul(self.rc0, rot_dq(self.units[1] * (E @ xe)))
        status = self.solver.stats()["return_status"]
        return elapsed, status, evaluate(self.prob, c, rc, self.t)


def _cols(a):
    import casadi as ca
    return [ca.DM(a[:, k:k + 1]) for k in range(4)]


def _rows(qs, idx):
    return [c[idx, :] for c in qs]


def _conj(qs):
    return [qs[0], -qs[1], -qs[2], -qs[3]]


def _qmul(a, b):
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return [aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw]


def _qexp(v):
    """Rotation vectors (K x 3 SX) -> quaternion columns; the 1e-24 keeps the derivative at 0."""
    import casadi as ca
    th = ca.sqrt(ca.sum2(v ** 2) + 1e-24)
    k = ca.sin(th / 2) / th
    return [ca.cos(th / 2), k * v[:, 0], k * v[:, 1], k * v[:, 2]]


def _qlog(qs):
    import casadi as ca
    w, u = qs[0], ca.horzcat(qs[1], qs[2], qs[3])
    n = ca.sqrt(ca.sum2(u ** 2) + 1e-24)
    return (2 * ca.atan2(n, w) / n) * u


def smooth_once(trials: int, factor: float) -> None:
    """``smooth`` on each trial once after a warm-up call, for an instruction count that a load
    does not move: under ``valgrind --tool=callgrind --toggle-collect=starmap_next`` only the
    measured calls are counted (they run inside ``itertools.starmap``, nothing else here does)."""
    import itertools

    cases = []
    for k in range(trials):
        t, truth = teleop_path(seed=k)
        cases.append((t, noisy(truth, seed=100 + k), limits_from(peaks(t, truth), factor)))
    for c in cases:
        smooth(*c)
    list(itertools.starmap(smooth, cases))


# ---- the table --------------------------------------------------------------------------------
METHODS = [("ours (banded + PIQP QP)", ours), ("banded only (no limits)", banded),
           ("OSQP, default tolerance", osqp), ("moving average, 21", moving_average),
           ("Savitzky-Golay, 31 / cubic", savitzky_golay)]


def run(trials: int, ipopt_trials: int, repeats: int, factor: float):
    """One row per method on ``trials`` recordings with limits ``factor`` x the true peaks."""
    cases = []
    for k in range(trials):
        t, truth = teleop_path(seed=k)
        cases.append((t, truth, noisy(truth, seed=100 + k), limits_from(peaks(t, truth), factor)))
    rows = []
    for name, f in METHODS:
        t, _, y, limits = cases[0]
        try:
            f(t, y, limits)                    # imports, casadi's plugins: not timed
        except ValueError:
            pass
        wall, cpu, et, er, worst, note = [], [], [], [], 0.0, ""
        for t, truth, y, limits in cases:
            for _ in range(repeats):
                w0, c0 = time.perf_counter(), time.process_time()
                try:
                    out_t, out = f(t, y, limits)
                except ValueError as e:
                    note = f"raised {type(e).__name__}: {e}"
                    break
                wall.append(time.perf_counter() - w0)
                cpu.append(time.process_time() - c0)
            else:
                a, b = errors(out, truth)
                et.append(a), er.append(b)
                worst = max(worst, violation(out_t, out, limits))
        rows.append((name, wall, cpu, et, er, worst, note))
    ip = []
    for t, truth, y, limits in cases[:ipopt_trials]:
        solver = Ipopt(t, y, limits)
        c0 = time.process_time()
        elapsed, status, out = solver.solve()
        ip.append((solver.build, elapsed, time.process_time() - c0, status, out, truth, t, limits))
    if ip:
        errs = [errors(x[4], x[5]) for x in ip]
        rows.append((f"IPOPT, nonlinear ({', '.join(sorted({x[3] for x in ip}))}; build "
                     f"{np.median([x[0] for x in ip]):.1f} s, not in the time)",
                     [x[1] for x in ip], [x[2] for x in ip], [e[0] for e in errs],
                     [e[1] for e in errs], max(violation(x[6], x[4], x[7]) for x in ip), ""))
    return rows


def table(rows) -> str:
    out = ["| method | wall (ms) | CPU (ms) | translation error median / max (mm) | rotation error "
           "median / max (deg) | worst limit violation |", "|---|---:|---:|---:|---:|---:|"]
    for name, wall, cpu, et, er, worst, note in rows:
        if note:
            out.append(f"| {name} | – | – | – | – | {note} |")
            continue
        et, er = np.concatenate(et) * 1e3, np.degrees(np.concatenate(er))
        out.append(f"| {name} | {np.median(wall) * 1e3:.1f} | {np.median(cpu) * 1e3:.1f} | "
                   f"{np.median(et):.3f} / {et.max():.3f} | {np.median(er):.3f} / {er.max():.3f} | "
                   f"{worst * 100:.2f} % |")
    return "\n".join(out)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--trials", type=int, default=5)
    ap.add_argument("--ipopt-trials", type=int, default=1)
    ap.add_argument("--repeats", type=int, default=5, help="timed calls per trial")
    ap.add_argument("--callgrind", type=float, metavar="FACTOR",
                    help="smooth the trials once with limits FACTOR x the true peaks, for an "
                         "instruction count, and exit (see smooth_once)")
    args = ap.parse_args(argv)
    if args.callgrind:
        smooth_once(args.trials, args.callgrind)
        return
    for factor, what in ((1.0, "limits = the true path's peaks (the recording obeys them)"),
                         (0.8, "limits = 0.8 x the true path's peaks (the operator moved faster "
                               "than the arm may: the error is mostly what the limits take)")):
        rows = run(args.trials, args.ipopt_trials, args.repeats, factor)
        print(f"\n500 poses at 100 Hz, noise rms 1 mm / 0.5 deg, {what}; {args.trials} trials x "
              f"{args.repeats} calls; load average {os.getloadavg()[0]:.2f}, {os.cpu_count()} CPUs")
        print(table(rows))


if __name__ == "__main__":
    main()
