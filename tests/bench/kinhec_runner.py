"""KinHEC's side of the KinHEC benchmark, run by an interpreter that has ``kinhec`` 1.1.0:

    PYTHON tests/bench/kinhec_runner.py plan SPEC.json OUT.json
    PYTHON tests/bench/kinhec_runner.py run SPEC.json IDS.json OUT.pkl [--no-baselines]

Not part of the dqpose package and imports nothing of it: ``bench_handeye_kinhec`` writes the tier
spec (the structure of KinHEC's ``configs/*.yaml``), asks for the plan, then has chunks of its
sequences generated here and solved by every KinHEC baseline under KinHEC's own protocol
(``kinhec.benchmark.evaluate_sequence``: keyframes ≥ 5° or 2 cm apart, consecutive motions for
the A X = X B solvers, absolute poses for the A X = Y B ones).

plan → a list of ``{id, track, level, robot, configuration, family}``, one per planned sequence.
run  → a pickled list, one dict per sequence id (plain Python and NumPy only):
    ``id``, ``A``/``B`` (k, 4, 4): the keyframe pairs of ``A_i X = Y B_i`` as the baselines get
    them; ``X``/``Y`` (4, 4) the truth; ``eye_in_hand``; ``outlier`` (k,) the generator's labels
    at the keyframes; ``scale``; ``robot_noise``/``camera_noise``: the generator's settings;
    ``baselines``: ``{solver: (rot_deg, trans_mm, error)}`` (NaN errors and the exception text
    when a solver raised or answered NaN; absent with ``--no-baselines``, which only generates);
    ``error``: why the sequence has no data ("" else).
"""
import json
import pickle
import sys

import numpy as np
from kinhec import benchmark, generate_sequence, motions
from kinhec.config import SequenceConfig
from kinhec.io import Sequence
from kinhec.plans import build_plan


def _plan(spec):
    return [c for cfgs in build_plan(spec).values() for c in cfgs]


def _keyframes(seq: Sequence):
    """The keyframe pairs and their outlier labels, selected exactly as the protocol's
    ``_keyframe_data`` selects them (which does not return the indices)."""
    valid = seq.paired_measurements(None)[2]
    A_abs, B_abs = seq.axyb_poses(None)
    outlier = np.asarray(seq.camera.outlier, bool)[valid]
    idx = motions.select_keyframes(A_abs, benchmark.KEYFRAME_MIN_ROT_DEG,
                                   benchmark.KEYFRAME_MIN_TRANS_M, benchmark.MAX_KEYFRAMES)
    if len(idx) < 3:
        idx = np.arange(len(A_abs))
    return A_abs[idx], B_abs[idx], outlier[idx]


def _run(cfg: SequenceConfig, baselines: bool = True) -> dict:
    out = {"id": cfg.sequence_id, "robot_noise": cfg.robot_noise,
           "camera_noise": cfg.camera_noise, "error": ""}
    rec = generate_sequence(cfg)
    seq = Sequence(rec.manifest, rec.robot_table, rec.camera_table)
    A, B, outlier = _keyframes(seq)
    out.update(A=A, B=B, outlier=outlier, X=seq.X, Y=seq.Y, eye_in_hand=seq.eye_in_hand,
               scale=seq.scale)
    if len(A) < 3:
        out["error"] = f"{len(A)} keyframes"
        return out
    if not baselines:
        return out
    rows = benchmark.evaluate_sequence(seq, list(benchmark.SOLVERS), sync="oracle",
                                       rng=np.random.default_rng(cfg.seed))
    out["baselines"] = {r["solver"]: (float(r.get("X_rot_err_deg", np.nan)),
                                      float(r.get("X_trans_err_mm", np.nan)), r["error"])
                        for r in rows}
    return out


def main(argv):
    baselines = "--no-baselines" not in argv
    argv = [a for a in argv if a != "--no-baselines"]
    if len(argv) < 4 or argv[1] not in ("plan", "run"):
        sys.exit(f"usage: {argv[0]} plan SPEC.json OUT.json | run SPEC.json IDS.json OUT.pkl "
                 f"[--no-baselines]")
    with open(argv[2]) as f:
        spec = json.load(f)
    plan = _plan(spec)
    if argv[1] == "plan":
        with open(argv[3], "w") as f:
            json.dump([{"id": c.sequence_id, "track": c.track, "level": c.level,
                        "robot": c.robot, "configuration": c.configuration,
                        "family": c.family} for c in plan], f)
        return
    with open(argv[3]) as f:
        wanted = json.load(f)
    by_id = {c.sequence_id: c for c in plan}
    with open(argv[4], "wb") as f:
        pickle.dump([_run(by_id[i], baselines) for i in wanted], f)


if __name__ == "__main__":
    main(sys.argv)
