"""The report of ``dqpose handeye solve``: the text (how the data was read, X and Z with their
standard deviations, each view's residual, the warnings, the error against a simulation's
truth), the result as JSON, and the files they and the plot are written to."""
from __future__ import annotations

import json
import math
import os
import re
import sys

import numpy as np

from dqpose import dq, lie
from dqpose.cli.common import fail
from dqpose.handeye.setups import EYE_IN_HAND, EYE_TO_HAND

_FRAMES = {EYE_IN_HAND: ("T_flange_camera", "T_base_target"),
           EYE_TO_HAND: ("T_base_camera", "T_flange_target")}


def with_image_names(text: str, names: list) -> str:
    """``pairs[3]`` in a message followed by the image it came from."""
    return re.sub(r"\b(pairs|base_flange|camera_target)\[(\d+)\]",
                  lambda m: f"{m.group(0)} ({names[int(m.group(2))]})"
                  if int(m.group(2)) < len(names) else m.group(0), text)


def _pose_lines(label: str, pose, cov) -> list[str]:
    from dqpose.drivers.rotvec import rotvec_from_quat
    q, t = dq.to_pose(pose)
    q = -q if q[0] < 0 else q
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    rv = np.degrees(rotvec_from_quat(q))
    return [f"{label}",
            f"  position   [{t[0] * 1e3:10.3f} {t[1] * 1e3:10.3f} {t[2] * 1e3:10.3f}] mm    "
            f"1 sigma [{sd[3] * 1e3:.3f} {sd[4] * 1e3:.3f} {sd[5] * 1e3:.3f}] mm",
            f"  rotation   [{rv[0]:10.4f} {rv[1]:10.4f} {rv[2]:10.4f}] deg (rotation vector)  "
            f"1 sigma [{np.degrees(sd[0]):.4f} {np.degrees(sd[1]):.4f} "
            f"{np.degrees(sd[2]):.4f}] deg",
            f"  quaternion [{q[0]:.8f} {q[1]:.8f} {q[2]:.8f} {q[3]:.8f}] (w, x, y, z)"]


def report(cal, views, names: list, skipped: list, truth=None) -> str:
    """The text report of a solve: how the data was read, X and Z with their standard
    deviations, the residual of each view, the views left out and why, the warnings, and the
    error against the truth of a simulated capture."""
    fx, fz = _FRAMES[cal.setup]
    rejected = {r.index: r.reason for r in cal.rejected}
    out = [f"{len(rejected)} left out by the robust solve"] if rejected else []
    out += [f"{len(skipped)} not detected"] if skipped else []
    lines = [f"hand-eye calibration, {cal.setup}: {len(names) - len(rejected)} views used of "
             f"{len(views.images)} images" + (f" ({'; '.join(out)})" if out else "")
             + f"; poses: {views.poses_file}"]
    lines += [f"note: {n}" for n in views.notes]
    lines += [f"not detected: {n}: {d}" for n, d in skipped]
    lines += [""] + _pose_lines(f"X = {fx}", cal.x, cal.covariance_x)
    lines += _pose_lines(f"Z = {fz}", cal.z, cal.covariance_z)
    lines.append("(1 sigma per axis of the covariance: rotation first, right perturbation "
                 "T * Exp(xi), in the pose's own frame)")
    res = np.asarray(cal.residuals, dtype=np.float64).reshape(-1, 2)
    loo = cal.leave_one_out if cal.leave_one_out is not None else np.full((len(res), 2), np.nan)
    lines += ["", "per view: its residual, and how far X moves when it is left out",
              f"{'view':>4s}  {'image':20s} {'residual deg':>12s} {'mm':>9s} "
              f"{'X moves deg':>12s} {'mm':>9s}"]
    for k, n in enumerate(names):
        tail = f"  left out: {rejected[k]}" if k in rejected else ""
        lines.append(f"{k:4d}  {n:20s} {math.degrees(res[k, 0]):12.4f} {res[k, 1] * 1e3:9.3f} "
                     f"{math.degrees(loo[k, 0]):12.4f} {loo[k, 1] * 1e3:9.3f}{tail}")
    keep = [k for k in range(len(res)) if k not in rejected]
    if keep:
        rms = np.sqrt(np.mean(res[keep] ** 2, axis=0))
        lines.append(f"RMS over the views used: {math.degrees(rms[0]):.4f} deg, "
                     f"{rms[1] * 1e3:.3f} mm")
    lines.append("")
    if cal.closed_form_x is not None:
        a = cal.agreement
        lines.append(f"closed form (Daniilidis) against the refined X: {math.degrees(a[0]):.4f} "
                     f"deg, {a[1] * 1e3:.3f} mm (NEES {a[2]:.2f})")
    lines.append(f"rotation excitation {math.degrees(cal.excitation):.2f} deg (near 0: rotation "
                 f"axes parallel), condition number {cal.rotation_condition:.3g}; "
                 + ("noise: each view's covariance as given" if cal.noise_model == "given" else
                    "noise estimated from the residuals")
                 + f", {cal.iterations} Gauss-Newton steps")
    if cal.reprojection is not None:
        lines.append(f"corner level: reprojection RMS per view {np.min(cal.reprojection):.3f}.."
                     f"{np.max(cal.reprojection):.3f} px, corner noise {cal.pixel_sigma:.3f} px"
                     + (f", focal lengths x {cal.focal_scale:.6f} +- {cal.focal_sigma:.6f}"
                        if cal.focal_sigma else ""))
    for r, a, d in cal.readings:
        lines.append(f"reading {r}: median residual {math.degrees(a):.4f} deg, {d * 1e3:.3f} mm")
    warnings = [f"warning: {with_image_names(w, names)}" for w in cal.warnings]
    lines += [""] + (warnings or ["no warnings"])
    if truth is not None:
        lines.append("")
        for label, est, cov, true in (("X", cal.x, cal.covariance_x, truth[0]),
                                      ("Z", cal.z, cal.covariance_z, truth[1])):
            xi = lie.se3_log(dq.mul(dq.inv(est), true))
            nees = float(xi @ np.linalg.solve(cov, xi))
            dt = np.linalg.norm(dq.to_pose(est)[1] - dq.to_pose(true)[1])
            lines.append(f"against the simulation's truth: {label} off by "
                         f"{math.degrees(np.linalg.norm(xi[:3])):.4f} deg, {dt * 1e3:.3f} mm "
                         f"(NEES {nees:.2f}; 6 expected, 22.5 the 99.9 % bound)")
    return "\n".join(lines) + "\n"


def result_json(cal, names: list) -> dict:
    """The calibration as JSON: the poses as the proto's Pose, covariances as 36 numbers."""
    from dqpose.cli.posefile import pose_json
    return {"setup": cal.setup, "x": pose_json(cal.x), "z": pose_json(cal.z),
            "covariance_x": np.asarray(cal.covariance_x).ravel().tolist(),
            "covariance_z": np.asarray(cal.covariance_z).ravel().tolist(),
            "covariance_convention": "6x6 row-major, rotation first [wx wy wz vx vy vz], right "
                                     "perturbation T * Exp(xi) (GTSAM Pose3)",
            "images": names,
            "residuals": np.asarray(cal.residuals).reshape(-1, 2).tolist(),
            "warnings": list(cal.warnings)}


def write(args, cal, views, names: list, truth, text: str) -> int:
    """The report, the result and the plot written where ``args`` say (next to the images by
    default); an exit code."""
    out = {k: getattr(args, k) or os.path.join(args.dir, default) for k, default in
           (("report", "handeye_report.txt"), ("plot", "handeye.png"),
            ("output", "handeye.json"))}
    try:
        with open(out["report"], "w", encoding="utf-8") as f:
            f.write(text)
        with open(out["output"], "w", encoding="utf-8") as f:
            json.dump(result_json(cal, names), f, indent=1)
        try:
            from dqpose.cli.plots import plot_calibration
            plot_calibration(out["plot"], cal, names,
                             title=f"dqpose handeye solve {args.dir} ({views.setup})",
                             truth=truth)
            print(f"plot: {out['plot']}", file=sys.stderr)
        except ModuleNotFoundError as e:
            from dqpose.errors import missing
            print(f"no plot: {missing(e)}", file=sys.stderr)
    except OSError as e:
        return fail("handeye solve", str(e))
    print(f"report: {out['report']}, result: {out['output']}", file=sys.stderr)
    return 0
