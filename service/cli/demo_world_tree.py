"""The frame tree of ``dqpose demo world``: a table fixed in the world (a static,
``WorldConfig.statics``), a mug standing on it, and a camera riding on the arm's tool
(``Source.parent`` = "tool", its extrinsic a hand-eye X with X's covariance) that sees the mug;
the world composes each of the camera's measurements with the tool's fused pose at its time, so
the mug's fused pose carries the arm's and X's uncertainty, and a Lookup of the mug in the
table's frame answers where it stands on the table.

The camera's measurements are simulated here (the truth through the tool's true pose, with
noise); the X the world is given is the true one moved by a draw of its own covariance, as a
hand-eye calibration's would be."""
from __future__ import annotations

import time

import numpy as np

from dqpose import dq, lie

#: the table in the world (its corner at the floor, turned 0.3 rad about z)
TABLE = dq.from_pose([np.cos(0.15), 0.0, 0.0, np.sin(0.15)], [0.40, -0.15, -0.02])
#: the mug on the table
MUG = dq.from_pose([1.0, 0.0, 0.0, 0.0], [0.06, 0.12, 0.0])
#: the camera in the tool's frame (T_tool_wrist: 5 cm off the flange's axis, looking along it)
X_TRUE = dq.from_pose([np.cos(0.05), 0.0, np.sin(0.05), 0.0], [0.0, 0.05, 0.03])
#: X's covariance as a hand-eye calibration gives it (rad, then m; rotation first)
X_SIGMA = (1e-3, 5e-4)
#: the camera's measurement noise (rad, m), one sigma per axis
WRIST_SIGMA = (2e-3, 1e-3)
WRIST_RATE = 10.0          # frames per second


def x_covariance() -> np.ndarray:
    return np.diag(np.repeat(np.square(X_SIGMA), 3))


def configured_x(rng: np.random.Generator) -> np.ndarray:
    """The X the world is given: the true one moved by a draw of its covariance."""
    return dq.mul(X_TRUE, lie.se3_exp(rng.normal(0.0, 1.0, 6) * np.repeat(X_SIGMA, 3)))


def frames(rng: np.random.Generator) -> dict:
    """``configure_world``'s arguments for the tree: the wrist camera riding on "tool", the
    table a static of the world."""
    from dqpose.frames import Static
    from dqpose.fusion import Source
    return {"sources": [Source("wrist", extrinsic=configured_x(rng), parent="tool",
                               extrinsic_covariance=x_covariance())],
            "statics": [Static("", "table", TABLE)]}


def wrist_reads(T_world_tool: np.ndarray, start: float, seconds: float, newest, rng):
    """The wrist camera's measurements of the mug (``T_wrist_mug``, its noise drawn) every
    1/WRIST_RATE s from ``start`` for ``seconds``, stamped with the clock, as ``Batch`` es;
    ``newest``: the time of the last one published."""
    from dqpose.rpc.client import Batch
    T_wrist_mug = dq.mul(dq.inv(dq.mul(T_world_tool, X_TRUE)), dq.mul(TABLE, MUG))
    cov = np.diag(np.repeat(np.square(WRIST_SIGMA), 3))
    k = 0
    while (t := start + k / WRIST_RATE) < start + seconds:
        time.sleep(max(0.0, t - time.time()))
        k += 1
        noise = lie.se3_exp(rng.normal(0.0, 1.0, 6) * np.repeat(WRIST_SIGMA, 3))
        newest.value = t
        yield Batch(dq.mul(T_wrist_mug, noise)[None], cov[None], None, ["wrist"], ["mug"],
                    np.array([t]))


def looked_up(client, target: str, source: str, truth: np.ndarray, start: float, what: str,
              where: str, out) -> tuple[float, float]:
    """Prints ``source`` looked up in ``target``'s frame (``what``: how it is called) against
    ``truth`` (``where``: what the truth is); returns its error and one sigma of its position
    (mm)."""
    from dqpose.cli.demo_fusion_scene import pose_error
    r = client.lookup(target, source)
    deg, mm = pose_error(r.pose, truth)
    s_rot, s_pos = lie.cov_sigmas(r.covariance)
    print(f"Lookup {what} at {r.time - start:.2f} s: {mm:.2f} mm, {deg:.3f} deg from {where} "
          f"(1 sigma {s_pos * 1e3:.2f} mm, {np.degrees(s_rot):.3f} deg)", file=out, flush=True)
    return mm, s_pos * 1e3


def report(client, start: float, out) -> tuple[float, float]:
    """Prints the world's frames (``dqpose world frames``) and the mug looked up in the table's
    frame against where it stands; returns its error and one sigma of its position (mm)."""
    from dqpose.cli.world import frames_text
    print("\nthe world's frames (dqpose world frames):\n" + frames_text(client.frames()),
          end="", file=out)
    return looked_up(client, "table", "mug", MUG, start, "mug in the table frame (seen by the "
                     "wrist camera riding on the tool)", "where it stands", out)
