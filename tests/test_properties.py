"""Table 1 of Kavan et al. measured on our blends (service/properties.py).

The 36 cells are compared with the paper one by one. Deliberately broken methods show that each
measurement can fail, and the ``dqpose properties`` command is run as a real subprocess.
"""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from dqpose import dq
from dqpose import properties as props

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def table() -> props.Table:
    return props.measure(trials=200, seed=0)


@pytest.mark.parametrize("prop", props.PROPERTIES)
@pytest.mark.parametrize("method", list(props.METHODS))
def test_cell_matches_paper(table, method, prop):
    cell = table.cells[method][prop]
    assert cell.holds == props.PAPER[prop][method], f"{method} {prop}: {cell.reason}"
    if cell.holds:
        assert cell.worst <= table.tol
    elif np.isfinite(cell.worst):
        # A failing cell fails by far more than rounding, or the tolerance would be the verdict.
        assert cell.worst > 1e3 * table.tol, cell.reason


def test_table_agrees_on_another_seed():
    assert props.measure(trials=64, seed=12345).mismatches() == []


# ---- broken methods: each measurement can fail --------------------------------------------

def _normalised(w):
    w = np.asarray(w, dtype=float)
    return w / w.sum(axis=-1, keepdims=True)


def _qmul(a, b):
    aw, av = a[..., :1], a[..., 1:]
    bw, bv = b[..., :1], b[..., 1:]
    return np.concatenate([aw * bw - np.sum(av * bv, axis=-1, keepdims=True),
                           aw * bv + bw * av + np.cross(av, bv)], axis=-1)


def _matrix_unchecked(q):
    """The unit formulas applied as they stand; dq.to_matrix rightly refuses a non-unit input."""
    w, x, y, z = np.moveaxis(q[..., :4], -1, 0)
    conj = q[..., :4] * [1.0, -1.0, -1.0, -1.0]
    t = 2.0 * _qmul(q[..., 4:], conj)[..., 1:]
    M = np.zeros(q.shape[:-1] + (4, 4))
    M[..., 0, :3] = np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z),
                              2 * (x * z + w * y)], -1)
    M[..., 1, :3] = np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z),
                              2 * (y * z - w * x)], -1)
    M[..., 2, :3] = np.stack([2 * (x * z - w * y), 2 * (y * z + w * x),
                              1 - 2 * (x * x + y * y)], -1)
    M[..., :3, 3] = t
    M[..., 3, 3] = 1.0
    return M


def unnormalised_sum(dqs, w):
    """DLB without the normalisation: the weighted sum is not a unit dual quaternion."""
    dqs = np.asarray(dqs)
    pivot = dqs[..., :1, :4]
    sign = np.where(np.sum(pivot * dqs[..., :4], axis=-1) < 0.0, -1.0, 1.0)
    return _matrix_unchecked(np.einsum("...n,...nk->...k", _normalised(w) * sign, dqs))


def dlb_no_hemisphere(dqs, w):
    """DLB without putting the inputs in one hemisphere: q and -q blend differently."""
    return dq.to_matrix(dq.normalize(np.einsum("...n,...nk->...k", _normalised(w), dqs)))


# A fixed frame, rotated and away from the origin, in which a decomposition blend is done.
_FRAME = dq.from_pose([np.cos(0.4), np.sin(0.4), 0.0, 0.0], [0.7, -0.3, 1.1])


def dec_in_other_frame(dqs, w):
    """Slerp of rotations and lerp of translations, both done in the frame ``_FRAME``."""
    inner = dq.mul(dq.mul(dq.conj(_FRAME), dqs), _FRAME)
    return dq.to_matrix(dq.mul(dq.mul(_FRAME, dq.dec(inner, w)), dq.conj(_FRAME)))


def eased_sclerp(dqs, w):
    """ScLERP at a smoothstep of the parameter: rigid, on the screw, but accelerating."""
    tau = _normalised(w)[..., 1]
    tau = tau * tau * (3.0 - 2.0 * tau)
    return dq.to_matrix(dq.blend(dqs, np.stack([1.0 - tau, tau], axis=-1), method="sclerp"))


@pytest.fixture(scope="module")
def broken() -> props.Table:
    return props.measure(trials=64, seed=0, methods={
        "unnormalised": unnormalised_sum, "no-hemisphere": dlb_no_hemisphere,
        "other-frame": dec_in_other_frame, "eased": eased_sclerp})


@pytest.mark.parametrize("method, prop", [
    ("unnormalised", "rigidity"),
    ("unnormalised", "const-speed"),   # the path is not rigid, so the property is undefined
    ("no-hemisphere", "shortest"),
    ("other-frame", "coord-inv"),
    ("other-frame", "bi-inv"),
    ("eased", "const-speed"),
])
def test_broken_method_fails(broken, method, prop):
    cell = broken.cells[method][prop]
    assert not cell.holds, cell.reason
    assert cell.worst > 1e3 * broken.tol, cell.reason


@pytest.mark.parametrize("method, prop", [
    # each broken method keeps the properties its defect does not touch
    ("no-hemisphere", "rigidity"),
    ("no-hemisphere", "bi-inv"),
    ("other-frame", "const-speed"),
    ("other-frame", "shortest"),
    ("eased", "rigidity"),
    ("eased", "shortest"),
    ("eased", "bi-inv"),
])
def test_broken_method_keeps_untouched_properties(broken, method, prop):
    assert broken.cells[method][prop].holds, broken.cells[method][prop].reason


def test_long_way_round_is_measured_along_the_path():
    # +170 and -170 deg about z: the principal logs blend through 0 (340 deg), the screw goes
    # through 180 (20 deg). Both paths keep their axis, so only the swept angle tells them apart.
    h = np.radians(85.0)
    pair = dq.from_pose([[np.cos(h), 0, 0, np.sin(h)], [np.cos(h), 0, 0, -np.sin(h)]],
                        [[0.1, 0.2, 0.3], [0.4, -0.2, 0.9]])[None]
    log = props._path_measurements(props.METHODS["Log"], pair, ["+-170deg"])
    sc = props._path_measurements(props.METHODS["ScLERP"], pair, ["+-170deg"])
    assert np.degrees(log.swept[0]) == pytest.approx(340.0, abs=1e-9)
    assert np.degrees(sc.swept[0]) == pytest.approx(20.0, abs=1e-9)
    assert log.axis_dev[0] < 1e-12 and sc.axis_dev[0] < 1e-12


def test_mismatch_is_reported(broken):
    table = props.measure(trials=16, seed=0, methods={"DLB": unnormalised_sum})
    assert ("DLB", "rigidity") in table.mismatches()
    text = props.format_table(table)
    assert "[+]!" in text and "disagree at DLB rigidity" in text


def test_bad_arguments_name_the_argument():
    with pytest.raises(ValueError, match="^trials:"):
        props.measure(trials=3)
    with pytest.raises(ValueError, match="^tol:"):
        props.measure(tol=0.0)


# ---- the command --------------------------------------------------------------------------

def _dqpose() -> list[str]:
    script = Path(sys.executable).with_name("dqpose")
    return [str(script)] if script.exists() else [sys.executable, "-m", "dqpose.cli"]


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(_dqpose() + ["properties", *args], cwd=ROOT, capture_output=True,
                          text=True, timeout=120)


def test_command_prints_the_table_and_exits_zero():
    out = _run()
    assert out.returncode == 0, out.stdout + out.stderr
    header = next(line for line in out.stdout.splitlines() if line.startswith("property"))
    assert header.split()[1:] == list(props.METHODS)
    for prop in props.PROPERTIES:
        assert any(line.startswith(prop) for line in out.stdout.splitlines()), prop
    assert "36/36 cells agree with the paper." in out.stdout


def test_command_exits_nonzero_when_a_cell_disagrees():
    # Below rounding no property can hold, so the paper's "+" cells disagree.
    out = _run("--tol", "1e-30", "--trials", "16")
    assert out.returncode == 1, out.stdout + out.stderr
    assert "!" in out.stdout and "disagree at" in out.stdout
