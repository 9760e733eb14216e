"""What the ChArUco detector's corners get wrong, against the truth of rendered views:
`.venv/bin/python -m tests.bench.bench_charuco_corners [--trials 200] [--blur 0.6 --noise 2]`.

The views are those of bench_handeye's end-to-end rows (the wrist scene of ``tests/_handeye.py``,
15 views a trial, seeds ``seed·1000 + trial``), rendered by ``drivers/sim/camera.py`` (clean
unless ``--blur``/``--noise``) and detected by ``drivers/camera.py``. Two rows: OpenCV's corners
as its ChArUco detector refines them, and ours (``CharucoCamera.detect``: the same corners
refined again in windows that keep off the markers); both go through the same PnP and
covariance.

Columns: the mean corner error (detected − true projection, px, with its standard error) —
a convention bias (half-pixel centres, the board's corner positions) would show here; the
largest mean over a 3×3 grid of image regions; the RMS error per coordinate; the **pull toward
the board's near side** (``tests/_handeye.near_side_pull``: a view's mean error along the
direction in which its board's scale grows), over all views and by the board's tilt from the
optical axis; the variance of a view's mean corner error over what independent errors of the
view's own RMS would give (x, y; 1 when the corners share nothing); and the mean NEES of each
view's pose under its reported covariance (6 for χ²₆; about 6.3 when the pixel variance is
estimated from ~42 residual degrees of freedom, as the detector does).
"""
from __future__ import annotations

import argparse
import os
import time

import numpy as np

from dqpose import dq, lie
from tests import _handeye
from tests.bench._table import markdown
from tests.bench.bench_handeye import CHARUCO_POSES, opencv_corners_camera

TILTS = ((0, 25), (25, 35), (35, 90))   # degrees: thirds of the wrist scene's views


def views(trials: int, seed: int, blur: float, noise: float):
    """Per detected view and row: (errors (n, 2), true projections, tilt in deg, pull, NEES)."""
    from dqpose.drivers.camera import CharucoCamera
    from dqpose.drivers.sim.camera import DEFAULT_INTRINSICS, BoardRenderer

    K = DEFAULT_INTRINSICS.K
    renderer = BoardRenderer()
    cams = {"OpenCV's corners": opencv_corners_camera(DEFAULT_INTRINSICS),
            "ours (refined off the markers)": CharucoCamera(DEFAULT_INTRINSICS)}
    rows = {name: [] for name in cams}
    rng = np.random.default_rng(seed)
    for k in range(trials):
        sc = _handeye.scene(CHARUCO_POSES, "eye_in_hand", "wrist", (0.0, 0.0), None,
                            seed=seed * 1000 + k)
        for T in sc.true_camera_target:
            img = renderer.render(T, blur=blur, noise=noise, rng=rng)
            tilt = float(np.degrees(np.arccos(abs(dq.to_matrix(T)[2, 2]))))
            for name, cam in cams.items():
                d = cam.detect(img)
                if not d.ok:
                    continue
                truth = _handeye.project(T, d.object_points, K)
                xi = lie.se3_log(dq.mul(dq.inv(d.pose), T))
                rows[name].append((d.image_points - truth, truth, tilt,
                                   _handeye.near_side_pull(T, d.object_points, d.image_points, K),
                                   float(xi @ np.linalg.solve(d.covariance, xi))))
    return rows


def _pm(values: np.ndarray) -> str:
    return f"{values.mean():+.4f} ± {values.std(ddof=1) / np.sqrt(len(values)):.4f}"


def render(rows: dict, size=(640, 480)) -> str:
    head = ["corners", "views", "mean error x / y (px)", "largest regional mean (px)",
            "RMS x / y (px)", "pull toward the near side (px)",
            *[f"pull, tilt {a}–{b}°" for a, b in TILTS], "view-mean variance ratio x / y",
            "mean NEES of a view"]
    lines = []
    for name, rs in rows.items():
        E = np.concatenate([r[0] for r in rs])
        P = np.concatenate([r[1] for r in rs])
        tilt = np.array([r[2] for r in rs])
        pull = np.array([r[3] for r in rs])
        cell = np.minimum((P / size * 3).astype(int), 2)
        regional = max(float(np.max(np.abs(E[np.all(cell == c, axis=1)].mean(axis=0))))
                       for c in np.unique(cell, axis=0))
        means = np.array([r[0].mean(axis=0) for r in rs])
        n = np.array([len(r[0]) for r in rs])[:, None]
        rms = np.array([np.sqrt(np.mean(r[0] ** 2)) for r in rs])[:, None]
        ratio = np.mean(means ** 2 * n / rms ** 2, axis=0)
        lines.append([name, str(len(rs)),
                      " / ".join(_pm(E[:, i]) for i in (0, 1)), f"{regional:.4f}",
                      " / ".join(f"{v:.4f}" for v in np.sqrt(np.mean(E ** 2, axis=0))),
                      _pm(pull), *[_pm(pull[(tilt >= a) & (tilt < b)]) for a, b in TILTS],
                      " / ".join(f"{v:.2f}" for v in ratio),
                      f"{np.mean([r[4] for r in rs]):.2f}"])
    return markdown(head, lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=200, help="trials of 15 views (default 200)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--blur", type=float, default=0.0, help="Gaussian blur sigma, px")
    ap.add_argument("--noise", type=float, default=0.0, help="noise sigma, grey levels")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    rows = views(args.trials, args.seed, args.blur, args.noise)
    print(f"ChArUco corners against the truth — {args.trials} trials × {CHARUCO_POSES} wrist "
          f"views, seed {args.seed}, blur {args.blur:g} px, noise {args.noise:g} grey levels, "
          f"load {os.getloadavg()[0]:.2f}")
    print(render(rows))
    print(f"({time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
    main()
