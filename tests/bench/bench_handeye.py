"""Benchmark of hand-eye calibration: `.venv/bin/python -m tests.bench.bench_handeye [--plot PATH]`.

Issue 11's comparison: ours (``dqpose.handeye.calibrate``) against OpenCV 4.x's five
``calibrateHandEye`` methods (Tsai, Park, Horaud, Andreff, Daniilidis) and its two
``calibrateRobotWorldHandEye`` methods (Shah, Li), on the same data in the same run.

OpenCV runs in an OpenCV 4.x environment of its own (:mod:`tests.bench.handeye_opencv`, which
also states its conventions); ``--opencv-python PATH`` uses another interpreter that has OpenCV
4.x; ``--no-opencv`` runs ours alone.

Scenes: ``tests/_handeye.py`` (the one generator): the wrist geometry (a camera 0.3–0.6 m from the
board) and OpenCV's own test geometry, eye-in-hand, {10, 20} poses × camera noise
{0.1°/0.5 mm, 0.5°/2 mm} per axis × robot noise {none, ``ROBOT_NOISE``} per axis, plus each
geometry eye-to-hand (20 poses, 0.1°/0.5 mm); seeds ``seed·1000 + trial``, the same for every
row. End to end: 15 wrist views of the 7×5 ChArUco board rendered without noise by
``drivers/sim/camera.py`` and detected by ``drivers/camera.py`` (``CharucoCamera.detect``), every
method on the detected poses (``--charuco-blur``/``--charuco-noise`` render them blurred and
noisy; ``--opencv-corners`` keeps OpenCV's ChArUco corners as they come, the detector before it
refined them off the markers).

Ours is run as a user runs it (noise estimated from the residuals) and, on the synthetic rows,
also told the noise the scene was drawn with (``camera_covariance``/``robot_covariance``): the
gap between the two is the cost of estimating the noise. On the ChArUco rows: given each view's
covariance from the detector (the robot exact, as it is there), and with the corners when
``calibrate`` takes them.

Columns: median rotation error (angle of R̂ᵀR, deg) and translation error (‖t̂ − t‖, mm) of X over
the trials, mean NEES of X (``ξᵀ P⁻¹ ξ``, ``ξ = Log(X̂⁻¹ X)``; 6 when the covariance is right; ours
only, OpenCV returns none), median wall time of one solve (ours from Python, refinement included;
OpenCV's the call inside its own process), and ``bad``: answers that are NaN, not a rotation (a
reflection or non-orthogonal), or the identity when the truth is not, and for ours refusals
(``Infeasible``). A bad answer counts as an infinite error in the medians.

A second table: every broken data set of ``tests/_handeye.py`` (``BROKEN``, ``broken()``: too
few poses, duplicates, pure translation, parallel axes, small rotations, a time shift, millimetres
as metres, inverted poses, the setup swapped, 20 % outliers, marker flips, ...; made from the
wrist scene, 20 poses, 0.1°/0.5 mm), what each method answers, and whether ours refused or warned
(issue 11: every one flagged, never NaN, never a silent identity).
"""
from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dqpose import dq
from tests import _handeye
from tests.bench._table import markdown
from tests.bench.fusion_scenes import _fmt_s, nees
from tests.bench.handeye_opencv import (  # noqa: F401 (OpenCVUnavailable, _inverse_matrix: tests)
    HERE,
    OPENCV,
    OPENCV_ENV,
    OPENCV_HAND_EYE,
    OpenCVUnavailable,
    _inverse_matrix,
    judge,
    opencv4_python,
    opencv_solve,
)

TRIALS = 200
CHARUCO_TRIALS = 50
CHARUCO_POSES = 15
GEOMETRIES = ("wrist", "opencv")
POSES = (10, 20)
CAMERA_NOISE = ((0.1, 0.5), (0.5, 2.0))   # (deg, mm) per axis
ROBOT_NOISE = (0.05, 0.2)                 # (deg, mm) per axis: an arm's pose, not its repeatability
OURS = "ours"
OURS_GIVEN = "ours (true noise given)"
OURS_COVARIANCE = "ours (detector covariances)"
OURS_CORNERS = "ours (corners)"


# ---- the run ------------------------------------------------------------------------------------
@dataclass
class Series:
    rot: list = field(default_factory=list)
    trans: list = field(default_factory=list)
    nees: list = field(default_factory=list)
    seconds: list = field(default_factory=list)
    bad: list = field(default_factory=list)      # reasons

    def add(self, X_hat, X, seconds=None, P=None, bad=""):
        if X_hat is None:
            self.rot.append(np.inf)
            self.trans.append(np.inf)
            self.bad.append(bad)
        else:
            r, t = _handeye.pose_error(X_hat, X)
            self.rot.append(r)
            self.trans.append(t)
            if P is not None:
                self.nees.append(nees(X_hat, P, X))
        if seconds is not None:
            self.seconds.append(seconds)


@dataclass(frozen=True)
class Case:
    geometry: str
    n: int
    camera_noise: tuple[float, float]
    robot_noise: tuple[float, float] | None
    setup: str = "eye_in_hand"

    @property
    def label(self) -> str:
        robot = "robot exact" if self.robot_noise is None else \
            f"robot {self.robot_noise[0]:g}°/{self.robot_noise[1]:g} mm"
        setup = "" if self.setup == "eye_in_hand" else ", eye-to-hand"
        return (f"{self.geometry}{setup}, {self.n} poses, camera {self.camera_noise[0]:g}°/"
                f"{self.camera_noise[1]:g} mm, {robot}")


def cases(geometries=GEOMETRIES, poses=POSES) -> list[Case]:
    """The issue's grid, eye-in-hand; and eye-to-hand at its first noise level (the other
    setup's conventions, on ours and OpenCV's, in the same run)."""
    grid = [Case(g, n, c, r) for g in geometries for n in poses for c in CAMERA_NOISE
            for r in (None, ROBOT_NOISE)]
    return grid + [Case(g, max(poses), CAMERA_NOISE[0], None, "eye_to_hand") for g in geometries]


def have_ours() -> bool:
    try:
        from dqpose import handeye  # noqa: F401
    except ImportError:
        return False
    return True


def ours(base_flange, camera_target, setup, **kwargs):
    """``(X, covariance, seconds, why)`` of ``calibrate``; X None and ``why`` the reason when it
    refuses (``Infeasible``) or answers NaN."""
    from dqpose import handeye
    from dqpose.errors import Infeasible
    t0 = time.perf_counter()
    try:
        cal = handeye.calibrate(base_flange, camera_target, setup, **kwargs)
    except Infeasible as e:
        return None, None, time.perf_counter() - t0, f"refused: {str(e).splitlines()[0][:60]}"
    seconds = time.perf_counter() - t0
    if not (np.all(np.isfinite(cal.x)) and np.all(np.isfinite(cal.covariance_x))):
        return None, None, seconds, "NaN"
    return cal.x, cal.covariance_x, seconds, ""


def add_ours(s: Series, truth, *args, **kwargs):
    X_hat, P, seconds, why = ours(*args, **kwargs)
    s.add(X_hat, truth, seconds, P, bad=why)


def run_case(case: Case, trials: int, seed: int, python: Path | None):
    setup = case.setup
    scenes = [_handeye.scene(case.n, setup, case.geometry, case.camera_noise, case.robot_noise,
                             seed=seed * 1000 + k) for k in range(trials)]
    res = {}
    if have_ours():
        run_ours(res, OURS, ((sc.x, sc.base_flange, sc.camera_target, setup, {})
                             for sc in scenes))
        # the same solver told the noise the scene was drawn with: what the model could do
        run_ours(res, OURS_GIVEN, ((sc.x, sc.base_flange, sc.camera_target, setup,
                                    dict(camera_covariance=sc.camera_covariance,
                                         robot_covariance=sc.robot_covariance))
                                   for sc in scenes))
    if python is not None:
        B = np.stack([sc.base_flange for sc in scenes])
        A = np.stack([sc.camera_target for sc in scenes])
        add_opencv(res, opencv_solve(python, B, A, setup), [sc.x for sc in scenes])
    return res


def add_opencv(res, solved, truths):
    for label, (X, _, seconds, errs) in solved.items():
        s = res.setdefault(label, Series())
        for k, truth in enumerate(truths):
            X_hat, why = (None, f"raised: {errs[k]}") if errs[k] else judge(X[k], truth)
            s.add(X_hat, truth, float(seconds[k]), bad=why)


# ---- end to end on rendered ChArUco images ------------------------------------------------
def opencv_corners_camera(intrinsics):
    """A ``CharucoCamera`` that keeps OpenCV's ChArUco corners as OpenCV refines them (before
    drivers/camera.py refined them again off the markers): the detector as it was."""
    from dqpose.drivers.camera import CharucoCamera

    class OpenCVCorners(CharucoCamera):
        def _refine_corners(self, gray, obj, img, rvec, tvec):
            return img
    return OpenCVCorners(intrinsics)


def charuco_views(trials: int, seed: int, n: int = CHARUCO_POSES, blur: float = 0.0,
                  noise: float = 0.0, opencv_corners: bool = False):
    """Per trial: the wrist scene (exact poses), every view rendered (clean unless ``blur`` px /
    ``noise`` grey levels) and detected (``opencv_corners``: with OpenCV's corners as they come).
    Returns ``(scene, kept indices, detected T_camera_target, corners per kept view, the
    detector's covariances)``; a view the detector rejects is left out, as a user would."""
    from dqpose.drivers.camera import CharucoCamera
    from dqpose.drivers.sim.camera import DEFAULT_INTRINSICS, BoardRenderer
    renderer = BoardRenderer()
    camera = (opencv_corners_camera if opencv_corners else CharucoCamera)(DEFAULT_INTRINSICS)
    rng = np.random.default_rng(seed)
    out = []
    for k in range(trials):
        # the scene's target frame is the board's frame (tests/_handeye.py, drivers/camera.py)
        sc = _handeye.scene(n, "eye_in_hand", "wrist", (0.0, 0.0), None, seed=seed * 1000 + k)
        kept, poses, corners, covariances = [], [], [], []
        for i, T in enumerate(sc.true_camera_target):
            det = camera.detect(renderer.render(T, blur=blur, noise=noise, rng=rng))
            if det.ok:
                kept.append(i)
                poses.append(det.pose)
                corners.append((det.object_points, det.image_points, DEFAULT_INTRINSICS.K))
                covariances.append(det.covariance)
        out.append((sc, np.array(kept), np.array(poses), corners, np.array(covariances)))
    return out


def run_ours(res: dict, label: str, jobs) -> None:
    """Row ``label``: ``calibrate`` on each ``(truth, base_flange, camera_target, setup, options)``
    of ``jobs``. A row whose options ``calibrate`` does not take yet (a TypeError, or a
    FieldError naming the option, on the first job) is left out with a note on stderr."""
    from dqpose.errors import FieldError, Infeasible
    jobs = list(jobs)
    truth, B, A, setup, options = jobs[0]
    if options:
        from dqpose import handeye
        try:
            handeye.calibrate(B, A, setup, **options)
        except TypeError as e:
            print(f"({label}: not run, {e})", file=sys.stderr)
            return
        except Infeasible:
            pass   # the option is taken; the refusal is counted below
        except FieldError as e:
            if str(e).startswith(tuple(options)):
                print(f"({label}: not run, {e})", file=sys.stderr)
                return
            raise
    res[label] = Series()
    for truth, B, A, setup, options in jobs:
        add_ours(res[label], truth, B, A, setup, **options)


def run_charuco(trials: int, seed: int, python: Path | None, **images):
    """Rows: ours on the detected poses (noise estimated), ours given the detector's covariance
    of each view (robot exact, as it is here), ours with the corners when it takes them, and
    every OpenCV method on the detected poses. ``images``: :func:`charuco_views`' options."""
    views = charuco_views(trials, seed, **images)
    res = {}
    if have_ours():
        options = {OURS: lambda v: {},
                   OURS_COVARIANCE: lambda v: dict(camera_covariance=v[4]),
                   OURS_CORNERS: lambda v: dict(corners=v[3])}
        for m, opt in options.items():
            run_ours(res, m, ((v[0].x, v[0].base_flange[v[1]], v[2], "eye_in_hand", opt(v))
                              for v in views))
    if python is not None:
        # one runner call per number of detected views (a batch is (k, n, ...)); the order of
        # the trials within a method's series does not matter to its medians
        for m in sorted({len(v[1]) for v in views}):
            group = [v for v in views if len(v[1]) == m]
            B = np.stack([v[0].base_flange[v[1]] for v in group])
            A = np.stack([v[2] for v in group])
            add_opencv(res, opencv_solve(python, B, A, "eye_in_hand"), [v[0].x for v in group])
    rejected = sum(CHARUCO_POSES - len(v[1]) for v in views)
    return res, rejected


# ---- broken data ---------------------------------------------------------------------------------
BROKEN_TRIALS = 10


def flagged(cal) -> bool:
    """Whether ours said something is wrong: a warning, or samples it rejected."""
    return bool(cal.warnings) or bool(getattr(cal, "rejected", ()))


def run_broken(trials: int, seed: int, python: Path | None):
    """Per kind: ours (refused / warned / silent, its error) and every OpenCV method's error."""
    out = {}
    for kind in _handeye.BROKEN:
        sets = [_handeye.broken(kind, 20, "eye_in_hand", seed * 1000 + k) for k in range(trials)]
        sets = [(b.base_flange, b.camera_target, b.setup, b.scene.x) for b in sets]
        row = {}
        if have_ours():
            from dqpose import handeye
            from dqpose.errors import Infeasible
            s, refused, warned, silent, first = Series(), 0, 0, 0, ""
            for B, A, setup, X in sets:
                try:
                    cal = handeye.calibrate(B, A, setup)
                except Infeasible as e:
                    refused += 1
                    first = first or str(e)
                    continue
                X_hat, why = judge(dq.to_matrix(cal.x), X)
                s.add(X_hat, X, bad=why)
                if flagged(cal):
                    warned += 1
                    first = first or (cal.warnings[0] if cal.warnings else "samples rejected")
                else:
                    silent += 1
            row[OURS] = dict(series=s, refused=refused, warned=warned, silent=silent,
                             message=first)
        if python is not None:   # one kind's sets share their shape and setup: one batch
            B, A = np.stack([b[0] for b in sets]), np.stack([b[1] for b in sets])
            add_opencv(row, opencv_solve(python, B, A, sets[0][2]), [b[3] for b in sets])
        out[kind.replace("_", " ")] = row
    return out


def _cell(s: Series) -> str:
    if not s.rot:
        return "—"
    kinds = ", ".join(sorted(set(b.split(":")[0] for b in s.bad)))
    if len(s.bad) == len(s.rot):
        return f"all {kinds}"
    text = f"{_med(s.rot)}° / {_med(s.trans)} mm"
    return text + (f" ({len(s.bad)} {kinds})" if s.bad else "")


def render_broken(results: dict, trials: int) -> str:
    methods = [OURS] + [m for m in OPENCV if any(m in r for r in results.values())]
    head = ["broken data", *methods]
    lines = []
    for kind, row in results.items():
        line = [kind]
        for m in methods:
            if m not in row:
                line.append("—")
            elif m == OURS:
                o = row[m]
                parts = [f"refused {o['refused']}/{trials}"] if o["refused"] else []
                if o["warned"]:
                    parts.append(f"warned {o['warned']}/{trials}")
                if o["silent"]:
                    parts.append(f"SILENT {o['silent']}/{trials}")
                if o["series"].rot:
                    parts.append(_cell(o["series"]))
                line.append(", ".join(parts))
            else:
                line.append(_cell(row[m]))
        lines.append(line)
    return markdown(head, lines)


# ---- the table and the targets ---------------------------------------------------------------
def _med(x):
    m = float(np.median(x)) if len(x) else np.nan
    if np.isinf(m) or np.isnan(m):
        return str(m)
    return f"{m:.4f}" if m < 0.1 else f"{m:.3f}" if m < 1e4 else f"{m:.2e}"


def render(results: dict) -> str:
    head = ["scene", "method", "median rot (deg)", "median trans (mm)", "mean NEES X",
            "time / solve", "bad"]
    lines = []
    for label, res in results.items():
        for m, s in res.items():
            bad = f"{len(s.bad)}/{len(s.rot)}"
            if s.bad:
                kinds = sorted(set(b.split(":")[0] for b in s.bad))
                bad += f" ({', '.join(kinds)})"
            lines.append([label, m, _med(s.rot), _med(s.trans),
                          f"{np.mean(s.nees):.2f}" if s.nees else "—", _fmt_s(s.seconds), bad])
    return markdown(head, lines)


def best_opencv(res):
    """The best OpenCV median rotation and translation (each over the methods, as the issue's
    figures are) and which methods gave them."""
    peers = [m for m in res if m in OPENCV]
    if not peers:
        return None
    r = min(peers, key=lambda m: np.median(res[m].rot))
    t = min(peers, key=lambda m: np.median(res[m].trans))
    return float(np.median(res[r].rot)), r, float(np.median(res[t].trans)), t


def _broken_line(broken_results: dict) -> str:
    """The target line of the broken data sets: each flagged, refused or warned, never NaN."""
    silent = {k: r[OURS]["silent"] for k, r in broken_results.items()
              if OURS in r and r[OURS]["silent"]}
    nan = {k: len(r[OURS]["series"].bad) for k, r in broken_results.items()
           if OURS in r and r[OURS]["series"].bad}
    return (f"- every broken data set flagged ({', '.join(broken_results)}), refused or "
            f"warned: " + ("PASS" if not silent else f"FAIL, silent on {silent}")
            + ("" if not nan else f"; bad answers {nan}: FAIL"))


def targets(results: dict, charuco_label: str | None, broken_results: dict | None = None) -> str:
    """Issue 11's targets, PASS/FAIL each, beside the best OpenCV method of the same run."""
    ok = lambda b: "PASS" if b else "FAIL"  # noqa: E731
    out = []
    goals = [(Case("wrist", 20, (0.1, 0.5), None), 0.058, 0.48, "0.059° / 0.64 mm"),
             (Case("wrist", 20, (0.5, 2.0), None), 0.27, 1.8, "0.30° / 2.79 mm"),
             (Case("opencv", 20, (0.1, 0.5), None), 0.01, 0.6, "0.06° / 4.2 mm")]
    rows = [(c.label, r, t, f) for c, r, t, f in goals]
    if charuco_label is not None:
        rows.append((charuco_label, 0.004, 0.02, "0.0065° / 0.054 mm"))
    for label, rot, trans, figure in rows:
        if label not in results:
            continue
        res = results[label]
        best = best_opencv(res)
        peer = "" if best is None else (f"; best OpenCV this run {best[0]:.4f}° ({best[1]}) / "
                                        f"{best[2]:.3f} mm ({best[3]})")
        if OURS not in res:
            out.append(f"- {label}: target ≤ {rot}° / ≤ {trans} mm: ours not run{peer}")
            continue
        for m in (OURS, OURS_GIVEN, OURS_COVARIANCE, OURS_CORNERS):
            if m not in res:
                continue
            r, t = float(np.median(res[m].rot)), float(np.median(res[m].trans))
            line = (f"- {label}: {m} {r:.4f}° / {t:.4f} mm, target ≤ {rot}° / ≤ {trans} mm "
                    f"(issue's best OpenCV: {figure}): {ok(r <= rot and t <= trans)}{peer}")
            if best is not None:
                line += (": ours " + ("better or equal" if r <= best[0] and t <= best[2] else
                                      "NOT better"))
            out.append(line)
    mine = {k: v[OURS] for k, v in results.items() if OURS in v}
    if not mine:
        return "\n".join(out)
    synthetic = {k: s for k, s in mine.items() if k != charuco_label}
    answered = {k: s for k, s in synthetic.items() if not s.bad}
    if answered:
        means = {k: float(np.mean(s.nees)) for k, s in answered.items()}
        off = [k for k, v in means.items() if abs(v - 6.0) > 1.0]
        n = min(len(s.nees) for s in answered.values())
        out.append(f"- mean NEES of X within 6 ± 1 ({n} trials a row, every synthetic row ours "
                   f"answered in full): {min(means.values()):.2f} to {max(means.values()):.2f}: "
                   f"{ok(not off)}" + (f"; outside: {'; '.join(f'{k} {means[k]:.2f}' for k in off)}"
                                       if off else ""))
        if OURS_GIVEN in results[next(iter(answered))]:
            given = {k: float(np.mean(results[k][OURS_GIVEN].nees)) for k in answered
                     if results[k][OURS_GIVEN].nees}
            out.append(f"  ({OURS_GIVEN}: {min(given.values()):.2f} to "
                       f"{max(given.values()):.2f})")
    if charuco_label in results:
        e2e = {m: float(np.mean(results[charuco_label][m].nees))
               for m in (OURS_COVARIANCE, OURS_CORNERS)
               if m in results[charuco_label] and results[charuco_label][m].nees}
        if e2e:
            n = min(len(results[charuco_label][m].nees) for m in e2e)
            out.append(f"- end to end, mean NEES of X within 6 ± 1 ({n} trials): "
                       + ", ".join(f"{m} {v:.2f}" for m, v in e2e.items()) + ": "
                       + ok(all(abs(v - 6.0) <= 1.0 for v in e2e.values())))
    t20 = [t for k, s in mine.items() if k != charuco_label and ", 20 poses," in k
           for t in s.seconds]
    if t20:
        med = float(np.median(t20))
        out.append(f"- solving 20 poses ≤ 50 ms including the refinement: median "
                   f"{med * 1e3:.1f} ms, 95th percentile "
                   f"{np.percentile(t20, 95) * 1e3:.1f} ms over "
                   f"{len(t20)} solves: {ok(med <= 0.05)}")
    if broken_results:
        out.append(_broken_line(broken_results))
    wrong = {k: sum(not b.startswith("refused") for b in s.bad) for k, s in mine.items()}
    wrong = {k: v for k, v in wrong.items() if v}
    out.append("- ours never NaN, never a reflection, never a silent identity: "
               + ("PASS" if not wrong else f"FAIL: {wrong}"))
    refused = {k: f"{len(s.bad)}/{len(s.rot)}" for k, s in synthetic.items() if s.bad}
    out.append("- ours answers every healthy data set (no refusal of the synthetic rows): "
               + ("PASS" if not refused else f"FAIL, refused {refused}"))
    return "\n".join(out)


def plot(path: str, results: dict, labels: list[str]):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    labels = [lb for lb in labels if lb in results]
    # log axes spanning less than a decade: label 2 and 5 between the powers of ten
    plain = matplotlib.ticker.FuncFormatter(lambda v, _: f"{v:g}")
    twos_and_fives = matplotlib.ticker.FuncFormatter(
        lambda v, _: f"{v:g}" if round(v / 10 ** np.floor(np.log10(v))) in (2, 5) else "")
    fig, axes = plt.subplots(len(labels), 2, figsize=(11, 2.9 * len(labels)), squeeze=False,
                             layout="constrained")
    for row, label in enumerate(labels):
        res = results[label]
        methods = list(res)
        for col, (attr, unit) in enumerate((("rot", "rotation (deg)"),
                                            ("trans", "translation (mm)"))):
            ax = axes[row, col]
            data = [np.clip(np.asarray(getattr(res[m], attr)), 1e-5, 1e3) for m in methods]
            ax.boxplot(data, orientation="horizontal", whis=(5, 95), showfliers=False)
            ax.set_xscale("log")
            ax.set_yticks(range(1, len(methods) + 1), methods, fontsize=8)
            ax.invert_yaxis()
            ax.xaxis.set_major_formatter(plain)
            ax.xaxis.set_minor_formatter(twos_and_fives)
            ax.tick_params(axis="x", which="both", labelsize=7)
            ax.grid(True, axis="x", which="both", alpha=0.3)
            ax.set_title(f"{label.split(' (')[0]}: {unit}" if col == 0 else unit, fontsize=8,
                         loc="left" if col == 0 else "center")
    fig.suptitle("Hand-eye calibration error of X per method (box: quartiles, whiskers: 5–95 %)",
                 fontsize=10)
    Path(path).resolve().parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    print(f"plot saved to {path}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=TRIALS,
                    help=f"per synthetic row (default {TRIALS}: the NEES target's count; 0 skips "
                         "them)")
    ap.add_argument("--charuco-trials", type=int, default=CHARUCO_TRIALS,
                    help=f"end-to-end trials of {CHARUCO_POSES} rendered views (default "
                         f"{CHARUCO_TRIALS}; 0 skips them)")
    ap.add_argument("--broken-trials", type=int, default=BROKEN_TRIALS,
                    help=f"seeded sets per broken kind (default {BROKEN_TRIALS}; 0 skips them)")
    ap.add_argument("--charuco-blur", type=float, default=0.0,
                    help="end to end: Gaussian blur of the renders, px (default 0: clean)")
    ap.add_argument("--charuco-noise", type=float, default=0.0,
                    help="end to end: noise of the renders, grey levels (default 0: clean)")
    ap.add_argument("--opencv-corners", action="store_true",
                    help="end to end: OpenCV's ChArUco corners as they come, not refined again "
                         "off the markers (the detector before wt-e2e)")
    ap.add_argument("--geometry", nargs="+", choices=GEOMETRIES, default=list(GEOMETRIES))
    ap.add_argument("--poses", nargs="+", type=int, default=list(POSES))
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--plot", metavar="PATH", help="also save the error distributions (PNG)")
    ap.add_argument("--opencv-python", metavar="PATH",
                    help="an interpreter with OpenCV 4.x (default: the benchmark's own "
                         f"environment in {OPENCV_ENV.relative_to(HERE.parents[1])}, created on "
                         "first use)")
    ap.add_argument("--no-opencv", action="store_true", help="ours alone")
    args = ap.parse_args(argv)
    python, version = None, None
    if not args.no_opencv:
        try:
            python, version = opencv4_python(args.opencv_python)
        except OpenCVUnavailable as e:
            sys.exit(f"bench_handeye: {e}")
    t0 = time.perf_counter()
    results = {}
    for case in cases(args.geometry, args.poses) if args.trials > 0 else ():
        results[case.label] = run_case(case, args.trials, args.seed, python)
    charuco_label = None
    if args.charuco_trials > 0:
        res, rejected = run_charuco(args.charuco_trials, args.seed, python,
                                    blur=args.charuco_blur, noise=args.charuco_noise,
                                    opencv_corners=args.opencv_corners)
        images = ("clean" if not (args.charuco_blur or args.charuco_noise) else
                  f"blur {args.charuco_blur:g} px, noise {args.charuco_noise:g}")
        charuco_label = (f"ChArUco rendered, {CHARUCO_POSES} views, {images}, end to end "
                         + ("(OpenCV's corners) " if args.opencv_corners else "")
                         + f"({rejected} of {CHARUCO_POSES * args.charuco_trials} views rejected)")
        results[charuco_label] = res
    print(f"dqpose hand-eye benchmark — {platform.processor() or platform.machine()}, "
          f"{os.cpu_count()} CPUs, load {os.getloadavg()[0]:.2f}, NumPy {np.__version__}, "
          + (f"OpenCV {version} (its own environment)" if version else "no OpenCV rows")
          + f"; {args.trials} trials per synthetic row, {args.charuco_trials} end to end, "
            f"seed {args.seed}")
    print(render(results))
    broken_results = None
    if args.broken_trials > 0:
        broken_results = run_broken(args.broken_trials, args.seed, python)
        print()
        print(f"Broken data ({args.broken_trials} seeded sets each of "
              f"tests/_handeye.py's broken(): "
              f"the wrist scene's 20 poses at 0.1°/0.5 mm broken as named; median error of X, "
              f"bad answers counted):")
        print(render_broken(broken_results, args.broken_trials))
        for kind, row in broken_results.items():
            if OURS in row and row[OURS]["message"]:
                print(f"- {kind}: ours says: {row[OURS]['message'].splitlines()[0][:160]}")
    print()
    print("Issue 11 targets:")
    print(targets(results, charuco_label, broken_results))
    print(f"({time.perf_counter() - t0:.0f} s)")
    if args.plot:
        main_rows = [Case("wrist", 20, (0.1, 0.5), None).label,
                     Case("wrist", 20, (0.5, 2.0), None).label,
                     Case("wrist", 20, (0.1, 0.5), ROBOT_NOISE).label,
                     Case("opencv", 20, (0.1, 0.5), None).label]
        plot(args.plot, results, main_rows + ([charuco_label] if charuco_label else []))


if __name__ == "__main__":
    main()
