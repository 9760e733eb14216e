"""The OpenCV 4.x peer of the hand-eye benchmark: its environment, its inputs in OpenCV's
conventions, its solves, and an answer judged against the truth.

OpenCV 5.0's wheel has neither hand-eye function (opencv#29565), so the benchmark creates its own
OpenCV 4.x environment once, ``tests/bench/_build/opencv4`` (a venv with
``opencv-python-headless<5`` and NumPy from PyPI; reused afterwards), and runs
``tests/bench/handeye_opencv4.py`` in it on the poses written to a temporary ``.npz``.

OpenCV's conventions (checked on exact data by tests/bench/test_bench_handeye.py: every method's
answer within 1e-8 of the truth; ~1e-15 measured):
``calibrateHandEye`` takes R/t_gripper2base (``T_base_flange``) and R/t_target2cam
(``T_camera_target``) and returns cam2gripper (``T_flange_camera``, our X for eye-in-hand); for
eye-to-hand the flange poses are passed inverted (``T_flange_base``) and it returns
``T_base_camera``.
``calibrateRobotWorldHandEye`` solves A·X = Z·B with world2cam = ``T_camera_target`` and
base2gripper = the inverse of what calibrateHandEye got; its gripper2cam is then our X⁻¹ and its
base2world our Z⁻¹, in both setups. ``method=`` is passed by keyword (#27625).
"""
from __future__ import annotations

import os
import subprocess
import tempfile
from pathlib import Path

import numpy as np

from dqpose import dq
from tests.bench._venv import BenchEnvUnavailable, bench_python, probe

HERE = Path(__file__).resolve().parent
RUNNER = HERE / "handeye_opencv4.py"
OPENCV_ENV = HERE / "_build" / "opencv4"
OPENCV_REQUIREMENTS = ("opencv-python-headless<5", "numpy")
OPENCV_HAND_EYE = ("TSAI", "PARK", "HORAUD", "ANDREFF", "DANIILIDIS")   # as handeye_opencv4.py
OPENCV_ROBOT_WORLD = ("SHAH", "LI")
OPENCV = tuple(f"OpenCV {m.title()}" for m in OPENCV_HAND_EYE + OPENCV_ROBOT_WORLD)


OpenCVUnavailable = BenchEnvUnavailable
_PROBE = "import cv2; cv2.calibrateHandEye; cv2.calibrateRobotWorldHandEye; print(cv2.__version__)"


def opencv4_python(python: str | None = None) -> tuple[Path, str]:
    """The interpreter with OpenCV 4.x and its version: ``python`` if given, else the benchmark's
    own environment, created on first use (:func:`tests.bench._venv.bench_python`)."""
    if python:
        version = probe(Path(python), _PROBE)
        if version is None:
            raise OpenCVUnavailable(f"--opencv-python {python}: no OpenCV with calibrateHandEye "
                                    f"and calibrateRobotWorldHandEye there")
        return Path(python), version
    return bench_python(OPENCV_ENV, OPENCV_REQUIREMENTS, _PROBE,
                        "OpenCV 5.0 has no calibrateHandEye",
                        "OpenCV's rows need it; --opencv-python PATH uses an interpreter that has "
                        "OpenCV 4.x, --no-opencv runs ours alone.")


def opencv_inputs(base_flange, camera_target, setup):
    """The runner's inputs in OpenCV's conventions (see the module doc), 4×4 matrices."""
    gripper2base = base_flange if setup == "eye_in_hand" else dq.inv(base_flange)
    return dict(gripper2base=dq.to_matrix(gripper2base), target2cam=dq.to_matrix(camera_target),
                base2gripper=dq.to_matrix(dq.inv(gripper2base)))


def opencv_solve(python: Path, base_flange, camera_target, setup) -> dict:
    """Every OpenCV method on ``k`` problems ``(k, n, 8)``: ``{label: (X, Z, seconds, errors)}``,
    X and Z ``(k, 4, 4)`` in our meaning (Z None for the calibrateHandEye methods), as OpenCV
    returned them (judged by :func:`judge`); ``seconds (k,)``, ``errors (k,)`` what raised."""
    with tempfile.TemporaryDirectory() as tmp:
        src, dst = os.path.join(tmp, "in.npz"), os.path.join(tmp, "out.npz")
        np.savez(src, **opencv_inputs(base_flange, camera_target, setup))
        r = subprocess.run([str(python), str(RUNNER), src, dst], capture_output=True, text=True)
        if r.returncode != 0:
            raise RuntimeError(f"{RUNNER.name} failed:\n{r.stderr[-2000:]}")
        with np.load(dst) as f:
            out = {k: f[k] for k in f.files}
    results = {}
    for name, label in zip(OPENCV_HAND_EYE + OPENCV_ROBOT_WORLD, OPENCV):
        X, Z = out[name + ".X"], None
        if name in OPENCV_ROBOT_WORLD:   # gripper2cam = X⁻¹, base2world = Z⁻¹
            X, Z = _inverse_matrix(X), _inverse_matrix(out[name + ".Z"])
        results[label] = (X, Z, out[name + ".seconds"], out[name + ".error"])
    return results


def _inverse_matrix(M):
    """Rigid inverses of (..., 4, 4) as given (R transposed, NaN kept): the answer is judged
    after, so this must not assume it is a rotation."""
    out = np.zeros_like(M)
    Rt = np.swapaxes(M[..., :3, :3], -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, M[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def judge(M: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray | None, str]:
    """A 4×4 answer as a pose, or None and why it is bad (NaN, not a rotation, identity)."""
    if not np.all(np.isfinite(M)):
        return None, "NaN"
    R = M[:3, :3]
    if np.linalg.det(R) < 0:
        return None, "reflection"
    if np.abs(R.T @ R - np.eye(3)).max() > 1e-6:
        return None, "not a rotation"
    X = dq.from_matrix(M)
    if np.allclose(M, np.eye(4), atol=1e-9) and not np.allclose(dq.to_matrix(truth), np.eye(4),
                                                               atol=1e-6):
        return None, "identity"
    return X, ""
