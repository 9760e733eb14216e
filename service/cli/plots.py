"""The PNG of ``dqpose plan --plot`` and ``dqpose smooth --plot``: the motion's position,
velocity, acceleration and jerk, linear and angular, each against its limit. What is drawn is
measured from the samples themselves (finite differences), not taken from the planner."""
from __future__ import annotations

import numpy as np

from service import trajectory


def plot_motion(path: str, times, poses, limits, title: str = "", raw=None) -> None:
    """Writes the PNG; ``raw`` ``(times, poses)``: the input of a smoothing, drawn under the
    positions. Needs matplotlib (``ModuleNotFoundError`` otherwise)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    d = trajectory.derivatives(times, poses)
    fig, ax = plt.subplots(4, 2, figsize=(11, 10), sharex=True)
    t = np.asarray(times)
    for c, (name, unit) in enumerate((("linear", "m"), ("angular", "rad"))):
        pos = d.position if c == 0 else d.rotation
        ax[0, c].plot(t, pos, lw=1)
        ax[0, c].legend(["x", "y", "z"], fontsize=7, loc="best")
        if raw is not None:
            r = trajectory.derivatives(*raw)
            ax[0, c].plot(raw[0], r.position if c == 0 else r.rotation, ".", ms=1.5,
                          color="0.6")
        ax[0, c].set_ylabel("position, m" if c == 0 else "rotation vector\nfrom the start, rad")
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
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
