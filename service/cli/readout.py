"""Poses as people read them, and as machines do, for ``world lookup``, ``world watch`` and ``demo
world``. For people: position in mm, rotation as a rotation vector (axis times angle) and as
roll-pitch-yaw (ROS's fixed axes, ``R = Rz(yaw) Ry(pitch) Rx(roll)``) in degrees, each angle
unwrapped against the body's row before (no jump between +180 and -180), one sigma in mm and
degrees (:func:`dqpose.lie.cov_sigmas`), times in seconds since the start, the sources in name
order. For machines (``--json``): SI units, absolute times, the pose with named components as the
pose files have it, and the covariance."""
from __future__ import annotations

import json
import math
import time

import numpy as np

from dqpose import dq, fusion, lie
from dqpose.cli.posefile import pose_json


def angles(pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(rotation vector, [roll, pitch, yaw])`` of a pose, in degrees (the rotation vector's
    angle in [0, 180])."""
    from dqpose.drivers.euler import sxyz_from_quat
    from dqpose.drivers.rotvec import rotvec_from_quat

    q, _ = dq.to_pose(pose)
    return np.degrees(rotvec_from_quat(q)), np.degrees(sxyz_from_quat(q))


def unwrap(rotvec: np.ndarray, rpy: np.ndarray, before) -> tuple[np.ndarray, np.ndarray]:
    """``rotvec`` and ``rpy`` (degrees) as near ``before`` (the last row's pair, or None) as the
    same rotation allows: the rotation vector's angle by whole turns along its axis, each of
    roll, pitch and yaw by whole turns."""
    if before is None:
        return rotvec, rpy
    theta = float(np.linalg.norm(rotvec))
    if theta > 0.0:
        axis = rotvec / theta
        rotvec = axis * (theta + 360.0 * round((float(axis @ before[0]) - theta) / 360.0))
    return rotvec, rpy + 360.0 * np.round((before[1] - rpy) / 360.0)


def _sources(f) -> str:
    verdicts = " ".join(f"{s.name}:{fusion.Verdict(s.verdict).name.lower()}"
                        for s in sorted(f.sources, key=lambda s: s.name))
    latencies = " ".join(f"{x.name}={x.value * 1e3:.1f}±{x.sigma * 1e3:.1f}ms"
                         for x in sorted(f.latencies, key=lambda x: x.name))
    return verdicts + (f"  latency {latencies}" if latencies else "")


class Readout:
    """A table of fused poses, a row per answer: times since ``start`` (None: the first
    answer's), and with ``delay`` the time from each answer's measurement time to its printing
    (for measurement times on this host's clock)."""

    def __init__(self, start: float | None = None, delay: bool = False):
        self.start, self.delay = start, delay
        self._before: dict = {}

    def header(self, extra: str = "") -> str:
        """The columns' names; ``extra``: those of :meth:`row`'s ``extra``."""
        return (f"{'t s':>8} {'body':>10} {'x mm':>9} {'y mm':>9} {'z mm':>9}  "
                f"{'rotation vector deg':^26} {'roll':>8} {'pitch':>7} {'yaw deg':>8} "
                f"{'σ mm':>7} {'σ deg':>7}" + (f" {'delay ms':>8}" if self.delay else "")
                + extra + "  NIS verdict by source, estimated latencies")

    def row(self, a, extra: str = "") -> str:
        """One :class:`~dqpose.rpc.client_types.StreamAnswer`; ``extra``: columns of the
        caller's before the sources (which vary in width)."""
        if self.start is None:
            self.start = a.time
        t = a.time - self.start
        if a.fused is None:
            return f"{t:8.3f} {a.body:>10}  error: {a.error}"
        f = a.fused
        _, p = dq.to_pose(f.mean)
        rotvec, rpy = unwrap(*angles(f.mean), self._before.get(a.body))
        self._before[a.body] = (rotvec, rpy)
        s_rot, s_pos = lie.cov_sigmas(f.covariance)
        delay = f" {(time.time() - a.time) * 1e3:8.0f}" if self.delay else ""
        return (f"{t:8.3f} {a.body:>10} {p[0] * 1e3:9.2f} {p[1] * 1e3:9.2f} {p[2] * 1e3:9.2f}  "
                f"{rotvec[0]:+8.2f} {rotvec[1]:+8.2f} {rotvec[2]:+8.2f} {rpy[0]:+8.2f} "
                f"{rpy[1]:+7.2f} {rpy[2]:+8.2f} {s_pos * 1e3:7.3f} {math.degrees(s_rot):7.4f}"
                f"{delay}{extra}  {_sources(f)}")


def answer_json(a) -> str:
    """One answer as a JSON line: ``body``, ``time`` (s), and the fused ``pose`` (named
    components), ``covariance`` (36, row-major, rotation first), ``sigma`` (``rotation`` rad,
    ``position`` m), ``sources`` and ``latencies``; or ``error``."""
    if a.fused is None:
        return json.dumps({"body": a.body, "time": a.time, "error": a.error})
    f = a.fused
    s_rot, s_pos = lie.cov_sigmas(f.covariance)
    return json.dumps({
        "body": a.body, "time": a.time, "pose": pose_json(f.mean),
        "covariance": np.asarray(f.covariance).ravel().tolist(),
        "sigma": {"rotation": float(s_rot), "position": float(s_pos)},
        "sources": [{"name": s.name, "verdict": fusion.Verdict(s.verdict).name.lower(),
                     "nis_mean": s.nis_mean, "count": s.count} for s in f.sources],
        "latencies": [{"source": x.name, "value": x.value, "sigma": x.sigma}
                      for x in f.latencies]})


def lookup_json(target: str, source: str, r) -> str:
    """A Lookup's answer as JSON: the frames, ``time`` (s), ``pose`` (named components),
    ``covariance`` and ``sigma`` as :func:`answer_json` has them."""
    s_rot, s_pos = lie.cov_sigmas(r.covariance)
    return json.dumps({"target": target, "source": source, "time": r.time,
                       "pose": pose_json(r.pose),
                       "covariance": np.asarray(r.covariance).ravel().tolist(),
                       "sigma": {"rotation": float(s_rot), "position": float(s_pos)}},
                      indent=1) + "\n"


def lookup_text(target: str, source: str, r) -> str:
    """A Lookup's answer for people."""
    q, p = dq.to_pose(r.pose)
    q = -q if q[0] < 0 else q
    rotvec, rpy = angles(r.pose)
    angle = float(np.linalg.norm(rotvec))
    axis = rotvec / angle if angle > 0 else np.array([0.0, 0.0, 1.0])
    s_rot, s_pos = lie.cov_sigmas(r.covariance)
    return "\n".join([
        f"T_{target}_{source}: {source} in {target}'s frame, at measurement time {r.time:.9g} s",
        f"  position        {p[0] * 1e3:.3f}  {p[1] * 1e3:.3f}  {p[2] * 1e3:.3f} mm",
        f"  rotation        {angle:.4f} deg about [{axis[0]:.5f}, {axis[1]:.5f}, {axis[2]:.5f}] "
        f"(rotation vector {rotvec[0]:.4f}, {rotvec[1]:.4f}, {rotvec[2]:.4f} deg)",
        f"  roll pitch yaw  {rpy[0]:.4f}  {rpy[1]:.4f}  {rpy[2]:.4f} deg (fixed axes, as ROS: "
        f"R = Rz(yaw) Ry(pitch) Rx(roll))",
        f"  1 sigma         {s_pos * 1e3:.4f} mm, {math.degrees(s_rot):.5f} deg (along the least "
        f"certain direction)",
        f"  quaternion      w {q[0]:.9f}  x {q[1]:.9f}  y {q[2]:.9f}  z {q[3]:.9f}",
        "(--json: the pose and its covariance for machines)"]) + "\n"
