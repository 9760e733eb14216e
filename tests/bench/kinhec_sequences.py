"""KinHEC's side of bench_handeye_kinhec: its interpreter, the settings it plans, its sequences.

KinHEC 1.1.0 is not a dependency of dqpose: it runs in an interpreter that imports it
(:func:`kinhec_python`, else the benchmark's own venv, ``tests/bench/_build/kinhec``), where
``kinhec_runner.py`` plans the tier :func:`spec` describes and generates and solves its sequences
(:func:`plan`, :func:`generate`); :func:`sequences` keeps them on disk so that ours is re-run on
the same ones.

Settings (:func:`spec`, the structure of KinHEC's tier files; seeds from KinHEC's global seed and
each sequence's id): ``noise`` UR5e, eye-in-hand and eye-to-hand, a continuous joint-sinusoid
trajectory (10 s, 30 Hz) and 20 look-at stations, robot noise r2, camera noise c1/c3/c5;
``motion`` free-floating stations in a cone of rotation axes (0°, 10°, 90°) and UR5e joint subsets
(parallel axes, wrist only, all); ``outliers`` UR5e, 30 stations, 0/10/30 % random poses or
planar flips, Gaussian or Student-t (3 dof) noise; ``monocular`` UR5e and free-floating, camera
translations at scale 0.5 and 2; ``repeats`` sequences per setting.
"""
from __future__ import annotations

import json
import pickle
import subprocess
import sys
import tempfile
from pathlib import Path

from tests.bench._venv import BenchEnvUnavailable, bench_python, probe

HERE = Path(__file__).resolve().parent
RUNNER = HERE / "kinhec_runner.py"
KINHEC_ENV = HERE / "_build" / "kinhec"
KINHEC_REQUIREMENTS = ("kinhec==1.1.0",)
_PROBE = "import kinhec; assert kinhec.__version__ == '1.1.0'; print(kinhec.__version__)"

KinhecUnavailable = BenchEnvUnavailable


def kinhec_python(python: str | None = None) -> tuple[Path, str]:
    """An interpreter with KinHEC 1.1.0 and its version: ``python`` if given, this one if it
    imports KinHEC, else the benchmark's own environment (created on first use)."""
    if python:
        version = probe(Path(python), _PROBE)
        if version is None:
            raise KinhecUnavailable(f"--kinhec-python {python}: no kinhec 1.1.0 there")
        return Path(python), version
    version = probe(Path(sys.executable), _PROBE)
    if version is not None:
        return Path(sys.executable), version
    return bench_python(KINHEC_ENV, KINHEC_REQUIREMENTS, _PROBE,
                        "KinHEC is a benchmark's dependency, not dqpose's",
                        "--kinhec-python PATH uses an interpreter that has kinhec 1.1.0.")


# ---- the settings --------------------------------------------------------------------------------
def spec(repeats: int) -> dict:
    """The tier KinHEC plans (its ``configs/*.yaml`` structure), ``repeats`` sequences a setting;
    the noise levels are KinHEC's own (rotation rad, translation m per axis)."""
    gauss = ["r2", "c2"]
    return {
        "tier": "dqpose", "global_seed": 20260909, "shard_size": 50,
        "repeats_multiplier": repeats, "robot_rate_cap_hz": 500,
        "defaults": {"camera": "hd", "target_eih": "checker_9x6_25mm",
                     "target_eth": "marker_3x3_30mm"},
        "noise_levels": {
            "robot": {"r0": [0.0, 0.0], "r1": [0.0002, 0.0001], "r2": [0.0005, 0.0003],
                      "r3": [0.002, 0.001], "r4": [0.005, 0.003]},
            "camera": {"c0": [0.0, [0.0, 0.0, 0.0]], "c1": [0.0005, [0.0003, 0.0003, 0.001]],
                       "c2": [0.002, [0.001, 0.001, 0.003]], "c3": [0.005, [0.003, 0.003, 0.01]],
                       "c4": [0.01, [0.006, 0.006, 0.02]], "c5": [0.02, [0.012, 0.012, 0.04]]}},
        "tracks": {
            "noise": {"robots": ["ur5e"], "configurations": ["eye_in_hand", "eye_to_hand"],
                      "families": [{"family": "joint_sinusoid", "mode": "continuous",
                                    "duration_s": 10, "camera_rate_hz": 30},
                                   {"family": "lookat", "mode": "stations", "n_stations": 20}],
                      "robot_levels": ["r2"], "camera_levels": ["c1", "c3", "c5"],
                      "repeats": 1},
            "motion": {"cone": {"cone_half_angle_deg": [0, 10, 90], "rot_angle_deg": [[15, 30]],
                                "n_waypoints": [20], "trans_range_m": 0.15, "repeats": 1,
                                "noise": gauss},
                       "joint_subsets": {"robots": ["ur5e"], "configurations": ["eye_in_hand"],
                                         "subsets": ["parallel", "wrist", "all"],
                                         "duration_s": 10, "camera_rate_hz": 30, "repeats": 1,
                                         "noise": gauss}},
            "outliers": {"robots": ["ur5e"], "configurations": ["eye_in_hand"],
                         "fraction": [0.0, 0.1, 0.3], "model": ["random_pose", "planar_flip"],
                         "student_t_dof": [None, 3], "n_stations": 30, "repeats": 1,
                         "noise": gauss},
            "monocular": {"robots": ["ur5e", "free6d"], "scale": [0.5, 2.0], "drift_std": [0.0],
                          "camera_model": ["se3_gaussian"], "vo_drift_std": [0.001, 0.002],
                          "duration_s": 10, "camera_rate_hz": 30, "repeats": 1, "noise": gauss},
        },
    }


def setting_of(p: dict) -> str:
    """A planned sequence's setting: everything but the repeat."""
    level = p["level"].replace("|", ", ")     # KinHEC's separator would split a table cell
    return f"{p['track']}: {level}; {p['robot']} {p['configuration']} {p['family']}"


def _runner(python: Path, *args) -> None:
    r = subprocess.run([str(python), str(RUNNER), *map(str, args)], capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"{RUNNER.name} {args[0]} failed:\n{r.stderr[-3000:]}")


def plan(python: Path, repeats: int) -> list[dict]:
    with tempfile.TemporaryDirectory() as tmp:
        src, dst = Path(tmp, "spec.json"), Path(tmp, "plan.json")
        src.write_text(json.dumps(spec(repeats)))
        _runner(python, "plan", src, dst)
        return json.loads(dst.read_text())


def generate(python: Path, repeats: int, ids: list[str], baselines: bool = True) -> list[dict]:
    """The sequences ``ids`` of the plan, generated and (unless not ``baselines``) solved by every
    baseline (the runner's ``run`` output)."""
    with tempfile.TemporaryDirectory() as tmp:
        src, idf, dst = Path(tmp, "spec.json"), Path(tmp, "ids.json"), Path(tmp, "out.pkl")
        src.write_text(json.dumps(spec(repeats)))
        idf.write_text(json.dumps(ids))
        _runner(python, "run", src, idf, dst, *([] if baselines else ["--no-baselines"]))
        with open(dst, "rb") as f:
            return pickle.load(f)


def sequences(python: Path, repeats: int, ids: list[str], baselines: bool = True,
              store: Path | None = None) -> list[dict]:
    """:func:`generate`'s sequences ``ids``, kept in the directory ``store`` (one pickle a
    sequence id) when given: those already there (with the baselines' answers, when
    ``baselines``) are read, not generated again, so a changed solver of ours is re-run on the
    same sequences at the cost of its own solves."""
    if store is None:
        return generate(python, repeats, ids, baselines)
    store.mkdir(parents=True, exist_ok=True)
    have = {}
    for i in ids:
        f = store / f"{i}.pkl"
        if f.exists():
            with open(f, "rb") as fh:
                seq = pickle.load(fh)
            if not baselines or "baselines" in seq or seq["error"]:
                have[i] = seq
    missing = [i for i in ids if i not in have]
    for seq in (generate(python, repeats, missing, baselines) if missing else []):
        with open(store / f"{seq['id']}.pkl", "wb") as fh:
            pickle.dump(seq, fh)
        have[seq["id"]] = seq
    return [have[i] for i in ids]
