"""The PNGs of the commands: ``dqpose plan --plot`` and ``dqpose smooth --plot``, the motion's
position, velocity, acceleration and jerk, linear and angular, each against its limit (measured
from the samples themselves, by finite differences, not taken from the planner); and
``dqpose handeye solve``'s, the residual of each view and the covariance ellipsoids of X and Z."""
from __future__ import annotations

import numpy as np

from dqpose import trajectory


def plot_motion(path: str, times, poses, limits, title: str = "", raw=None,
                note: str = "") -> None:
    """Writes the PNG of :func:`motion_figure`. Needs matplotlib (``ModuleNotFoundError``
    otherwise)."""
    import matplotlib.pyplot as plt

    fig = motion_figure(times, poses, limits, title, raw, note)
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _rotation_from(poses, reference) -> np.ndarray:
    """Rotation vectors ``Log(R_k R_ref^T)`` (base frame) of ``poses`` from ``reference``'s
    orientation: one origin for every curve drawn together (the smoothed path need not start
    where the recording does)."""
    from dqpose import dq

    r = np.asarray(poses, dtype=np.float64).reshape(-1, 8).copy()
    r[:, 4:] = 0.0
    ref = np.zeros(8)
    ref[:4] = np.asarray(reference, dtype=np.float64)[:4]
    return 2.0 * dq.log(dq.mul(dq.normalize(r), dq.conj(dq.normalize(ref))))[:, :3]


def motion_figure(times, poses, limits, title: str = "", raw=None, note: str = ""):
    """The figure: position, velocity, acceleration and jerk, linear and angular, each against
    its limit; ``raw`` ``(times, poses)``: the input of a smoothing, drawn under the positions,
    both orientations as rotation vectors from the recording's first one; ``note`` under the
    title."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    d = trajectory.derivatives(times, poses)
    reference = np.asarray(poses if raw is None else raw[1], dtype=np.float64).reshape(-1, 8)[0]
    fig, ax = plt.subplots(4, 2, figsize=(11, 10), sharex=True)
    t = np.asarray(times)
    for c, (name, unit) in enumerate((("linear", "m"), ("angular", "rad"))):
        pos = d.position if c == 0 else _rotation_from(poses, reference)
        ax[0, c].plot(t, pos, lw=1)
        ax[0, c].legend(["x", "y", "z"], fontsize=7, loc="best")
        if raw is not None:
            ax[0, c].plot(raw[0], (_positions(raw[1]) if c == 0
                                   else _rotation_from(raw[1], reference)),
                          ".", ms=1.5, color="0.6")
        ax[0, c].set_ylabel("position, m" if c == 0 else
                            "rotation vector from the\n" +
                            ("recording's start, rad" if raw is not None else "start, rad"))
        rows = ((d.velocity, d.angular_velocity, "velocity", 1, "velocity"),
                (d.acceleration, d.angular_acceleration, "acceleration", 2, "acceleration"),
                (d.jerk, d.angular_jerk, "jerk", 3, "jerk"))
        for lin, ang, what, order, key in rows:
            a = ax[order, c]
            values = np.linalg.norm(lin if c == 0 else ang, axis=1)
            mid = (t[:len(values)] + t[order:order + len(values)]) / 2   # differences' centres
            a.plot(mid, values, lw=1)
            bound = getattr(limits, f"max_{name}_{key}")
            if bound:
                a.axhline(bound, color="r", ls="--", lw=1, label="limit")
                a.legend(fontsize=7, loc="upper right")
            a.set_ylabel(f"|{what}|, {unit}/s" + ("" if order == 1 else f"^{order}"))
        ax[0, c].set_title(name)
        ax[3, c].set_xlabel("time, s")
    fig.suptitle(title + (f"\n{note}" if note else ""), fontsize=10 if note else None)
    fig.tight_layout()
    return fig


def _positions(poses) -> np.ndarray:
    """Positions ``(N, 3)`` of dual quaternions ``(N, 8)``."""
    from dqpose import dq

    return dq.to_pose(np.asarray(poses, dtype=np.float64).reshape(-1, 8))[1]


def plot_calibration(path: str, cal, names, title: str = "", truth=None) -> None:
    """Writes the PNG of a hand-eye calibration (:class:`dqpose.handeye.Calibration`): the
    residual of each view (rotation, translation; views the robust solve left out in red) and
    the 3-sigma ellipsoids of X's and Z's covariances, rotation (deg) and translation (mm),
    about the estimate in its own frame (the right perturbation); ``truth`` ``(x, z)``, when
    known (a simulation), is drawn where it lies: ``truth = estimate * Exp(xi)``. Needs
    matplotlib."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    res = np.asarray(cal.residuals, dtype=np.float64).reshape(-1, 2)
    left_out = {r.index for r in cal.rejected}
    colours = ["tab:red" if k in left_out else "tab:blue" for k in range(len(res))]
    fig = plt.figure(figsize=(11, 10))
    for c, (values, label) in enumerate(((np.degrees(res[:, 0]), "rotation residual, deg"),
                                         (res[:, 1] * 1e3, "translation residual, mm"))):
        a = fig.add_subplot(3, 2, c + 1)
        a.bar(np.arange(len(values)), values, color=colours)
        a.set_xticks(np.arange(len(values)))
        a.set_xticklabels(names, rotation=90, fontsize=6)
        a.set_ylabel(label)
        if left_out:
            a.set_title("red: left out by the robust solve", fontsize=8)
    u, v = np.meshgrid(np.linspace(0, 2 * np.pi, 30), np.linspace(0, np.pi, 15))
    sphere = np.stack([np.cos(u) * np.sin(v), np.sin(u) * np.sin(v), np.cos(v)])
    from dqpose import dq, lie
    offsets = [None, None] if truth is None else \
        [lie.se3_log(dq.mul(dq.inv(est), true)) for est, true in zip((cal.x, cal.z), truth)]
    for r, (pose, cov) in enumerate((("X", cal.covariance_x), ("Z", cal.covariance_z))):
        cov = np.asarray(cov, dtype=np.float64).reshape(6, 6)
        for c, (block, scale, unit) in enumerate(((slice(0, 3), np.degrees(1.0), "deg"),
                                                  (slice(3, 6), 1e3, "mm"))):
            a = fig.add_subplot(3, 2, 3 + 2 * r + c, projection="3d")
            w, V = np.linalg.eigh(cov[block, block] * scale ** 2)
            axes = V * (3.0 * np.sqrt(np.clip(w, 0.0, None)))
            e = np.einsum("ij,jkl->ikl", axes, sphere)
            a.plot_wireframe(e[0], e[1], e[2], lw=0.4, color="tab:blue")
            m = float(np.abs(e).max()) or 1.0
            if offsets[r] is not None:
                p = offsets[r][block] * scale
                a.scatter(*p, color="tab:red", s=20, label="truth")
                a.legend(fontsize=7, loc="upper left")
                m = max(m, float(np.abs(p).max()))
            for setter in (a.set_xlim, a.set_ylim, a.set_zlim):
                setter(-m, m)
            a.set_xlabel(unit, fontsize=7)
            a.tick_params(labelsize=6)
            what = "rotation" if c == 0 else "translation"
            a.set_title(f"{pose}: 3-sigma {what}, {unit} (largest {3 * np.sqrt(w.max()):.3g})",
                        fontsize=9)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
