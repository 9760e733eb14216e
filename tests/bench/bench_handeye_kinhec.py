"""Hand-eye calibration on KinHEC 1.1.0, an external benchmark:
`nice -n 10 .venv/bin/python -m tests.bench.bench_handeye_kinhec [--full] [--jobs N] [--plot PATH]`.

KinHEC (``pip install kinhec==1.1.0``) generates hand-eye sequences with ground truth from seeded
recipes and runs eleven baseline solvers under one protocol (keyframes ≥ 5° or 2 cm apart;
consecutive motions for Tsai, Park–Martin, Horaud, Daniilidis, Andreff, Andreff with scale,
Park–Martin + LM, RANSAC + Park–Martin; absolute poses for Shah, Li, Shah + LM). It is not a
dependency of dqpose: the benchmark uses an interpreter that imports it (``--kinhec-python``, or
this one if it can), else makes its own venv, ``tests/bench/_build/kinhec`` (once, from PyPI), and
runs ``tests/bench/kinhec_runner.py`` there to plan, generate and solve; ours
(``dqpose.handeye.calibrate``) runs here on the same keyframes, as absolute pose pairs.

Conventions (KinHEC's README §12, ours in :mod:`dqpose.handeye`): KinHEC's ``A_i X = Y B_i`` with
``A_i = T_base_ee``; eye-in-hand ``B_i = T_cam_target⁻¹``, ``X = T_ee_cam`` (our x),
``Y = T_base_target`` (our z); eye-to-hand ``B_i = T_cam_marker``, ``X = T_ee_marker`` (our z),
``Y = T_base_cam`` (our x). Errors are KinHEC's, on its X: the angle of R̂ᵀR (deg) and ‖t̂ − t‖ (mm).

Settings: :func:`tests.bench.kinhec_sequences.spec` (tracks ``noise``, ``motion``, ``outliers``,
``monocular``); ``--repeats N`` sequences per setting (3 by default, 20 with ``--full``).

Ours runs in two modes: ``estimated`` (the noise estimated from the residuals, as a user runs it)
and ``given`` (the generator's true covariances, as the CLI passes the detector's: per sample
``blockdiag(σr², Rᵢᵀ diag(σt²) Rᵢ)`` for the camera, ×ν/(ν−2) under Student-t tails, translations
×scale² on a monocular camera; ``diag(σr², σt²)`` for the robot; not run on a camera with VO drift,
which has no Gaussian equivalent).

Columns, per setting and method: median and 90th percentile of the rotation (deg) and translation
(mm) errors of X; ``fail``: refusals (``ValueError``, ours) or raised/NaN answers (baselines),
counted as an infinite error; for ours the mean NEES of X (``ξᵀP⁻¹ξ``, ξ = Log(X̂⁻¹X), 6 when the
covariance is right), ``silent``: answers with NEES > 50 that carry no warning naming some
samples (one naming every sample, as a rescale does, names no suspect),
``Δ vs best``: the median of the paired differences ours − best baseline (the baseline with the
lowest median translation error) with its bootstrap 95 % interval (translation, mm), and
``misses``: the targets of issue 24 the row misses (:func:`targets`).
"""
from __future__ import annotations

import argparse
import os
import pickle
import platform
import re
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from dqpose import dq
from dqpose.handeye import EYE_IN_HAND, EYE_TO_HAND, calibrate
from tests import _handeye
from tests.bench._table import markdown
from tests.bench.fusion_scenes import nees
from tests.bench.kinhec_sequences import (
    KinhecUnavailable,
    kinhec_python,
    plan,
    sequences,
    setting_of,
)

BASELINES = ("tsai_lenz", "park_martin", "horaud_dornaika", "daniilidis", "andreff",
             "andreff_scale", "park_martin+lm", "ransac_park_martin", "shah", "li_kronecker",
             "shah+lm")
RANSAC = "ransac_park_martin"
MODES = ("estimated", "given")
OURS = tuple(f"ours ({m})" for m in MODES)
REPEATS, FULL_REPEATS = 3, 20
SILENT_NEES = 50.0
BOOTSTRAP = 2000
# the degenerate settings, where the right answer is a refusal: the error targets do not apply
DEGENERATE = ("cone=0,", "subset=parallel")
_NAMES_SAMPLES = re.compile(r"\bsamples? (\d+(?:, \d+)*)")


def names_suspects(warning: str, n: int) -> bool:
    """Whether ``warning`` names some of the ``n`` samples but not all (a rescale names every
    sample: it says the data are off, not which)."""
    m = _NAMES_SAMPLES.search(warning)
    return m is not None and len(m.group(1).split(", ")) < n


# ---- ours ----------------------------------------------------------------------------------------
def given_noise(seq: dict, camera_target: np.ndarray):
    """The generator's true noise as ``calibrate``'s covariances (camera per sample, robot), or
    None when the camera's noise has no Gaussian equivalent (VO drift)."""
    cn, rn = seq["camera_noise"], seq["robot_noise"]
    if cn["model"] not in ("se3_gaussian", "none"):
        return None
    dof = cn.get("student_t_dof")
    tails = dof / (dof - 2.0) if dof else 1.0     # the variance of a Student-t draw
    R = dq.to_matrix(camera_target)[:, :3, :3]
    sr = np.broadcast_to(np.asarray(cn["rot_std_rad"], float), (3,)) ** 2 * tails
    st = np.broadcast_to(np.asarray(cn["trans_std_m"], float), (3,)) ** 2 * tails
    st = st * seq["scale"] ** 2
    C = np.zeros((len(R), 6, 6))
    C[:, :3, :3] = np.diag(sr)
    C[:, 3:, 3:] = np.swapaxes(R, 1, 2) @ np.diag(st) @ R
    C[:, :3, :3] += 1e-18 * np.eye(3)      # c0: a noise-free camera is still a covariance
    C[:, 3:, 3:] += 1e-18 * np.eye(3)
    robot = None
    if "se3_gaussian" in rn["models"] and (rn["rot_std_rad"] > 0 or rn["trans_std_m"] > 0):
        robot = np.diag([rn["rot_std_rad"] ** 2] * 3 + [rn["trans_std_m"] ** 2] * 3)
    return C, robot


@dataclass
class Answer:
    """One solve of ours: errors on KinHEC's X (inf when refused), NEES, what it said."""
    rot: float = np.inf
    trans: float = np.inf
    nees: float = np.nan
    status: str = "ok"           # "ok", "refused: ...", "crashed: ...", "n/a"
    named: bool = False          # a warning names samples
    warnings: tuple = ()
    sequence: str = ""           # KinHEC's sequence id

    @property
    def silent(self) -> bool:
        return self.status == "ok" and self.nees > SILENT_NEES and not self.named


def solve_ours(seq: dict, mode: str) -> Answer:
    A = dq.from_matrix(seq["A"])
    B = dq.from_matrix(seq["B"])
    eih = seq["eye_in_hand"]
    camera_target = dq.inv(B) if eih else B
    kwargs = {}
    if mode == "given":
        noise = given_noise(seq, camera_target)
        if noise is None:
            return Answer(status="n/a")
        kwargs = dict(camera_covariance=noise[0], robot_covariance=noise[1])
    truth = dq.from_matrix(seq["X"])
    try:
        cal = calibrate(A, camera_target, EYE_IN_HAND if eih else EYE_TO_HAND, **kwargs)
    except ValueError as e:
        return Answer(status=f"refused: {str(e).splitlines()[0]}")
    except Exception as e:     # a crash is a result too: counted, never stops the benchmark
        return Answer(status=f"crashed: {type(e).__name__}: {e}")
    X, P = (cal.x, cal.covariance_x) if eih else (cal.z, cal.covariance_z)
    rot, trans = _handeye.pose_error(X, truth)
    try:
        e = nees(X, P, truth)
    except np.linalg.LinAlgError:
        e = np.inf
    return Answer(rot, trans, e, "ok", any(names_suspects(w, len(A)) for w in cal.warnings),
                  tuple(cal.warnings))


def evaluate(seq: dict, modes=MODES) -> dict:
    """Every method's result on one generated sequence: ``{method: Answer}`` (ours only in
    ``modes``, "n/a" in the others)."""
    out = {}
    for name in BASELINES:
        if "baselines" not in seq and not seq["error"]:      # generated without them
            out[name] = Answer(status="n/a")
            continue
        rot, trans, err = seq.get("baselines", {}).get(name, (np.nan, np.nan, seq["error"]))
        ok = np.isfinite(rot) and np.isfinite(trans)
        out[name] = Answer(rot if ok else np.inf, trans if ok else np.inf,
                           status="ok" if ok else f"failed: {err or 'NaN'}")
    for mode, label in zip(MODES, OURS):
        out[label] = (Answer(status="n/a") if mode not in modes else
                      solve_ours(seq, mode) if not seq["error"]
                      else Answer(status=f"refused: {seq['error']}"))
    return out


def _chunk(args) -> list[tuple[str, dict]]:
    python, repeats, ids, baselines, store, modes = args
    out = []
    for seq in sequences(python, repeats, ids, baselines, store):
        answers = evaluate(seq, modes)
        for a in answers.values():
            a.sequence = seq["id"]
        out.append((seq["id"], answers))
    return out


def run(python: Path, repeats: int, select: str | None = None, jobs: int = 1,
        progress=None, ids=None, baselines: bool = True, store: Path | None = None,
        modes=MODES) -> dict[str, dict[str, list[Answer]]]:
    """``{setting: {method: [Answer per sequence]}}`` over the planned settings matching the
    regular expression ``select`` (all by default), and of those only the sequences ``ids`` when
    given; the baselines not run unless ``baselines``, ours in ``modes``; the sequences kept in
    ``store`` (:func:`sequences`)."""
    planned = [p for p in plan(python, repeats) if (not select or re.search(select, setting_of(p)))
               and (ids is None or p["id"] in ids)]
    by_setting: dict[str, list[str]] = {}
    for p in planned:
        by_setting.setdefault(setting_of(p), []).append(p["id"])
    # a chunk never mixes settings, so one slow setting does not hold the others' results back
    chunks = [ids[i:i + 5] for ids in by_setting.values() for i in range(0, len(ids), 5)]
    setting = {p["id"]: setting_of(p) for p in planned}
    results: dict[str, dict[str, list[Answer]]] = {s: {} for s in by_setting}
    tasks = [(python, repeats, c, baselines, store, modes) for c in chunks]
    if jobs > 1:
        with ProcessPoolExecutor(jobs) as ex:
            done = ex.map(_chunk, tasks)
            outs = list(_progress(done, len(tasks), progress))
    else:
        outs = list(_progress(map(_chunk, tasks), len(tasks), progress))
    for out in outs:
        for sid, answers in out:
            for m, a in answers.items():
                results[setting[sid]].setdefault(m, []).append(a)
    return results


def _progress(it, n, progress):
    t0 = time.perf_counter()
    for k, x in enumerate(it, 1):
        if progress:
            print(f"[{k}/{n} chunks, {time.perf_counter() - t0:.0f} s]", file=progress,
                  flush=True)
        yield x


# ---- statistics and targets ----------------------------------------------------------------------
def paired_median_ci(ours: np.ndarray, best: np.ndarray, seed: int = 0,
                     n: int = BOOTSTRAP) -> tuple[float, float, float]:
    """The median of ``ours − best`` and its percentile-bootstrap 95 % interval (pairs resampled
    together; an infinite error, a refusal, stays infinite)."""
    with np.errstate(invalid="ignore"):
        d = np.asarray(ours, float) - np.asarray(best, float)
    d = np.where(np.isnan(d), np.inf, d)      # both failed: not better than the baseline
    rng = np.random.default_rng(seed)
    # order statistics, never an average of two: a refusal (inf) next to a baseline's failure
    # (-inf) must not make a NaN
    boots = np.quantile(d[rng.integers(0, len(d), (n, len(d)))], 0.5, axis=1, method="lower")
    lo, hi = np.quantile(boots, [0.025, 0.975], method="lower")
    return float(np.quantile(d, 0.5, method="lower")), float(lo), float(hi)


@dataclass
class Row:
    """One method on one setting."""
    rot: np.ndarray
    trans: np.ndarray
    answers: list = field(default_factory=list)

    @staticmethod
    def of(answers: list) -> "Row":
        return Row(np.array([a.rot for a in answers]), np.array([a.trans for a in answers]),
                   answers)

    @property
    def ran(self) -> bool:
        return any(a.status != "n/a" for a in self.answers)

    @property
    def failed(self) -> int:
        return sum(a.status not in ("ok", "n/a") for a in self.answers)

    @property
    def silent(self) -> int:
        return sum(a.silent for a in self.answers)

    def mean_nees(self) -> float:
        v = [a.nees for a in self.answers if a.status == "ok"]
        return float(np.mean(v)) if v else np.nan

    def p(self, q: float, which: str = "trans") -> float:
        return float(np.percentile(getattr(self, which), q, method="lower"))


def best_baseline(rows: dict[str, Row]) -> str | None:
    """The baseline with the lowest median translation error (None when none ran)."""
    ran = [m for m in BASELINES if m in rows and rows[m].ran]
    return min(ran, key=lambda m: (rows[m].p(50), rows[m].p(50, "rot"))) if ran else None


def gaussian(setting: str) -> bool:
    return (setting.startswith(("noise:", "motion:"))
            or (setting.startswith("outliers:") and "fraction=0.0" in setting
                and "gaussian" in setting))


def silent_applies(setting: str) -> bool:
    """Issue 24's settings for zero silent contaminations: Gaussian noise (a monocular camera's
    too) and outliers."""
    return (gaussian(setting) or with_outliers(setting)
            or (setting.startswith("monocular:") and "se3_gaussian" in setting))


def with_outliers(setting: str) -> bool:
    return setting.startswith("outliers:") and "fraction=0.0" not in setting


def targets(setting: str, rows: dict[str, Row], label: str) -> dict[str, str]:
    """Issue 24's targets ``label`` misses on ``setting``: ``{target: why}`` (empty: all met)."""
    r, misses = rows[label], {}
    if not r.ran:
        return misses
    best = best_baseline(rows)
    if best is not None and not any(d in setting for d in DEGENERATE):
        for which, unit in (("trans", "mm"), ("rot", "deg")):
            m, lo, hi = paired_median_ci(getattr(r, which), getattr(rows[best], which))
            if lo > 0:
                misses[f"median {which}"] = f"+{m:.3g} {unit} [{lo:.3g}, {hi:.3g}] vs {best}"
        if r.p(90) > 1.2 * rows[best].p(90):
            misses["p90"] = f"{r.p(90):.3g} mm > 1.2 × {best}'s {rows[best].p(90):.3g}"
    if silent_applies(setting) and r.silent:
        misses["silent"] = f"{r.silent} silent contaminations"
    if with_outliers(setting):
        solved = 1 - r.failed / len(r.answers)
        if solved < 0.95:
            misses["solved"] = f"solved {solved:.0%} < 95 %"
        if rows[RANSAC].ran and r.p(50) >= rows[RANSAC].p(50):
            misses["vs RANSAC"] = f"median {r.p(50):.3g} mm ≥ RANSAC's {rows[RANSAC].p(50):.3g}"
    n = len(r.answers)
    if label == OURS[1] and gaussian(setting) and n >= 50:
        tol = 3 * np.sqrt(12 / n)
        if abs(r.mean_nees() - 6) > tol:
            misses["NEES"] = f"mean {r.mean_nees():.3g} outside 6 ± {tol:.2g}"
    return misses


def pooled_nees(summary: dict[str, dict[str, Row]]) -> str:
    """The mean NEES of X with the noise given pooled over the Gaussian settings' answers, against
    issue 24's 6 ± 0.5, and how many settings of N ≥ 50 miss 6 ± 3·√(12/N)."""
    rows = [rows[OURS[1]] for s, rows in summary.items() if gaussian(s) and rows[OURS[1]].ran]
    v = [a.nees for r in rows for a in r.answers if a.status == "ok"]
    if not v:
        return ""
    big = [r for r in rows if len(r.answers) >= 50]
    out = (f"mean NEES of X with the noise given, pooled over {len(v)} answers on {len(rows)} "
           f"Gaussian settings: {np.mean(v):.3g} (target 6 ± 0.5: "
           f"{'met' if abs(np.mean(v) - 6) <= 0.5 else 'missed'})")
    if big:
        miss = sum(abs(r.mean_nees() - 6) > 3 * np.sqrt(12 / len(r.answers)) for r in big)
        out += (f"; per setting (N ≥ 50, 6 ± 3·√(12/N)): {len(big) - miss} of {len(big)} "
                f"settings within")
    return out


def summarise(results) -> dict[str, dict[str, Row]]:
    return {s: {m: Row.of(a) for m, a in res.items()} for s, res in results.items()}


def _err(r: Row, q: float) -> str:
    rot, trans = r.p(q, "rot"), r.p(q)
    if not np.isfinite(trans):
        return "∞"
    return f"{rot:.3g}° / {trans:.3g} mm"


def render(summary: dict[str, dict[str, Row]]) -> str:
    head = ["setting", "method", "n", "median", "p90", "fail", "mean NEES", "silent",
            "Δ trans vs best [95 % CI]", "misses"]
    lines = []
    for s, rows in summary.items():
        best = best_baseline(rows)
        for m in OURS + BASELINES:
            r = rows[m]
            if not r.ran:
                lines.append([s, m, str(len(r.answers))] + ["—"] * 7)
                continue
            ours = m in OURS
            d = ""
            if ours and best is not None:
                med, lo, hi = paired_median_ci(r.trans, rows[best].trans)
                d = f"{med:+.3g} mm [{lo:+.3g}, {hi:+.3g}]"
            fails = f"{r.failed}/{len(r.answers)}" if r.failed else "0"
            lines.append([s, m + (" ★" if m == best else ""), str(len(r.answers)),
                          _err(r, 50), _err(r, 90), fails,
                          f"{r.mean_nees():.3g}" if ours else "",
                          str(r.silent) if ours else "", d,
                          "; ".join(targets(s, rows, m)) if ours else ""])
    return markdown(head, lines)


def _cell(r: Row) -> str:
    return f"{_err(r, 50)} ({r.p(90):.3g} mm)" if r.ran else "—"


def _delta(r: Row, best: Row) -> str:
    if not r.ran:
        return "—"
    med, lo, hi = paired_median_ci(r.trans, best.trans)
    return f"{med:+.3g} [{lo:+.3g}, {hi:+.3g}]"


def _pair(rows: dict[str, Row], f) -> str:
    return " / ".join(f(rows[m]) if rows[m].ran else "—" for m in OURS)


def render_brief(summary: dict[str, dict[str, Row]]) -> str:
    """One line a setting: ours in both modes beside the best baseline."""
    head = ["setting", "n", "best baseline: median (p90)", *(f"{m}: median (p90)" for m in OURS),
            "fail est / given", "mean NEES est / given", "silent est / given",
            *(f"Δ trans {m} [95 % CI]" for m in MODES), "misses"]
    lines = []
    for s, rows in summary.items():
        best = best_baseline(rows)
        misses = [f"{m.split()[1][1:-1]}: {k}" for m in OURS for k in targets(s, rows, m)]
        lines.append([s, str(len(rows[OURS[0]].answers)),
                      f"{best}: {_cell(rows[best])}" if best else "— (not run)",
                      *(_cell(rows[m]) for m in OURS), _pair(rows, lambda r: str(r.failed)),
                      _pair(rows, lambda r: f"{r.mean_nees():.3g}"),
                      _pair(rows, lambda r: str(r.silent)),
                      *(_delta(rows[m], rows[best]) if best else "—" for m in OURS),
                      "; ".join(misses)])
    return markdown(head, lines)


def plot(summary: dict[str, dict[str, Row]], path: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tracks = sorted({s.split(":")[0] for s in summary},
                    key=["noise", "motion", "outliers", "monocular"].index)
    fig, axes = plt.subplots(len(tracks), 1, figsize=(12, 3.6 * len(tracks)), squeeze=False)
    for ax, track in zip(axes[:, 0], tracks):
        settings = [s for s in summary if s.startswith(track + ":")]
        x = np.arange(len(settings))
        for m in BASELINES:
            y = [summary[s][m].p(50) if summary[s][m].ran else np.nan for s in settings]
            ax.plot(x, y, "o", color="0.7", ms=4, label="KinHEC baselines" if m == BASELINES[0]
                    else None)
        best = [best_baseline(summary[s]) for s in settings]
        ax.plot(x, [summary[s][b].p(50) if b else np.nan for s, b in zip(settings, best)], "_",
                color="k", ms=18, mew=2, label="best baseline")
        for m, c in zip(OURS, ("tab:red", "tab:blue")):
            y = [summary[s][m].p(50) if summary[s][m].ran else np.nan for s in settings]
            ax.plot(x + 0.12, y, "D", color=c, ms=6, label=m)
        ax.set_yscale("log")
        ax.set_ylabel("median X error (mm)")
        ax.set_xticks(x, [s.split(": ", 1)[1] for s in settings], rotation=20, ha="right",
                      fontsize=7)
        ax.set_title(f"KinHEC 1.1.0, track {track} (∞: more than half refused, off the axis)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--full", action="store_true",
                    help=f"{FULL_REPEATS} sequences per setting (default {REPEATS})")
    ap.add_argument("--repeats", type=int, help="sequences per setting")
    ap.add_argument("--select", help="only the settings matching this regular expression")
    ap.add_argument("--jobs", type=int, default=1, help="processes (default 1)")
    ap.add_argument("--kinhec-python", help="an interpreter that has kinhec 1.1.0")
    ap.add_argument("--no-baselines", action="store_true",
                    help="generate the sequences and solve ours only (NEES, refusals, our "
                         "errors; no comparison)")
    ap.add_argument("--modes", default=",".join(MODES),
                    help=f"ours in these modes, comma-separated (default {','.join(MODES)})")
    ap.add_argument("--sequences", help="a directory that keeps every generated sequence: "
                                        "those there are read, not generated again")
    ap.add_argument("--plot", help="save the plot of the medians here (PNG)")
    ap.add_argument("--save", help="pickle every answer here "
                                   "({setting: {method: [Answer as a dict]}})")
    ap.add_argument("--load", help="no run: the table (and plot) of answers saved by --save")
    ap.add_argument("--brief", action="store_true",
                    help="one line a setting (ours and the best baseline) instead of every method")
    args = ap.parse_args(argv)
    repeats = args.repeats or (FULL_REPEATS if args.full else REPEATS)
    table = render_brief if args.brief else render
    if args.load:
        with open(args.load, "rb") as f:
            saved = pickle.load(f)
        summary = summarise({s: {m: [Answer(**a) for a in v] for m, v in r.items()}
                             for s, r in saved.items()})
        print(f"dqpose hand-eye on KinHEC: the answers saved in {args.load} (★: the best "
              f"baseline)\n")
        print(table(summary))
        print("\n" + pooled_nees(summary))
        if args.plot:
            plot(summary, args.plot)
        return
    try:
        python, version = kinhec_python(args.kinhec_python)
    except KinhecUnavailable as e:
        sys.exit(f"bench_handeye_kinhec: {e}")
    t0 = time.perf_counter()
    results = run(python, repeats, args.select, args.jobs, progress=sys.stderr,
                  baselines=not args.no_baselines,
                  store=Path(args.sequences) if args.sequences else None,
                  modes=args.modes.split(","))
    wall = time.perf_counter() - t0
    if args.save:
        with open(args.save, "wb") as f:
            # plain dicts: Answer is __main__'s class when run with -m
            pickle.dump({s: {m: [asdict(a) for a in v] for m, v in r.items()}
                         for s, r in results.items()}, f)
    summary = summarise(results)
    n = sum(len(next(iter(r.values())).answers) for r in summary.values())
    print(f"dqpose hand-eye on KinHEC {version} — {platform.processor() or platform.machine()}, "
          f"{os.cpu_count()} cores, {args.jobs} job(s): {n} sequences in {len(summary)} "
          f"settings, {wall:.0f} s (★: the best baseline)\n")
    print(table(summary))
    print("\n" + pooled_nees(summary))
    if args.plot:
        plot(summary, args.plot)
        print(f"\nplot: {args.plot}")


if __name__ == "__main__":
    main()
