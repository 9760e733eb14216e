"""Table 1 of Kavan et al. (*Dual Quaternions for Rigid Transformation Blending*) measured on
dqpose.

Every cell is computed from the code: each blending method is run on many seeded random inputs
plus adversarial ones, the deviation from the property is measured, and the cell is ``+`` when the
worst deviation over all trials is within ``tol``. A single violating trial makes the cell ``-``
(a property is a "for all inputs" statement). ``PAPER`` holds the paper's values, typed in only as
the reference the measurement is compared with.

Definitions (the paper's, section 2.1 and Table 1):

* rigidity: the blend is a rigid motion, ``R^T R = I``, ``det R = 1``, bottom row ``[0 0 0 1]``.
* bi-invariance: ``blend(r q_i) = r blend(q_i)`` and ``blend(q_i r) = blend(q_i) r``.
* coordinate invariance: ``blend(T q_i T^-1) = T blend(q_i) T^-1``.
* n > 2: the method blends more than two poses.
* constant speed / shortest path: for two poses M0, M1 and the path ``Phi(t)`` (weights
  ``(1 - t, t)``), decompose ``M0^-1 Phi(t)`` as a screw: rotation angle ``alpha(t)``, axis
  direction ``a(t)``, translation ``delta(t)`` along the axis in direction ``d(t)``. Constant speed:
  ``alpha`` and ``delta`` have constant derivatives. Shortest path: ``a`` and ``d`` constant and
  ``alpha(1)`` within ``[-pi, pi]``. Both assume a rigid interpolant; where ``Phi(t)`` is not rigid
  (Lin) the properties do not hold by definition.

  ``a(t)`` is the axis *direction*, not the axis line: the paper marks Dec shortest-path, and
  Dec's rotation turns about a fixed direction while its screw axis line drifts (by metres for
  the pairs used here), whereas ScLERP and DLB keep the line too. ``delta`` is the translation
  *along* the screw axis, not the length of the translation vector: a screw motion's translation
  vector turns with the rotation, so with that reading ScLERP itself would fail both properties.
  ``alpha(1)`` is the rotation swept along the path (unwrapped), not the angle of
  ``M0^-1 Phi(1)``, which is folded into ``[0, pi]`` and would hide a path the long way round.

Run ``dqpose properties`` to print the table; it exits non-zero when any cell disagrees with the
paper.
"""
from __future__ import annotations

import time
import zlib
from dataclasses import dataclass, field
from typing import Callable, Iterable, Mapping

import numpy as np

from dqpose import dq

__all__ = [
    "Method", "Cell", "Table", "METHODS", "PROPERTIES", "PAPER", "DEFAULT_TOL",
    "measure", "measure_method", "format_table",
]

# (dqs (..., n, 8), weights (..., n)) -> 4x4 matrices (..., 4, 4). Matrices, not dual quaternions,
# so Lin's non-rigid blend can be measured on the same footing as the rigid ones.
Method = Callable[[np.ndarray, np.ndarray], np.ndarray]

def _blended_matrix(name: str) -> Method:
    if name == "lin":  # the raw blend: the table measures Lin, not its projection
        return dq.lin
    return lambda dqs, w: dq.to_matrix(dq.blend(dqs, w, method=name))


# Labelled as in the paper's tables (dq.METHODS, in its order).
METHODS: dict[str, Method] = {m.label: _blended_matrix(name) for name, m in dq.METHODS.items()}

PROPERTIES = ("rigidity", "bi-inv", "coord-inv", "n>2", "const-speed", "shortest")

# The reference: Table 1 of the paper, as printed (its columns are in the order of dq.METHODS:
# Lin, Dec, Log, ScLERP, DLB, DIB).
PAPER: dict[str, dict[str, bool]] = {
    prop: dict(zip(METHODS, (c == "+" for c in row.split())))
    for prop, row in {
        "rigidity":    "- + + + + +",
        "bi-inv":      "+ - - + + +",
        "coord-inv":   "+ - + + + +",
        "n>2":         "+ + + - + +",
        "const-speed": "- + - + - +",
        "shortest":    "- + - + + +",
    }.items()
}

# Absolute on matrix entries (metres, radians) for inputs of order 1 m, relative for speeds. The
# iterative methods (Dec, DIB) stop at a 1e-12 step, so 1e-9 leaves room for their error and is
# still ~1e8 times smaller than any deviation a method that lacks a property shows.
DEFAULT_TOL = 1e-9
# Samples of t in [0, 1] for the path properties.
PATH_SAMPLES = 64


@dataclass(frozen=True)
class Cell:
    """One measured cell: does the property hold, the worst deviation seen, and why."""
    holds: bool
    worst: float
    reason: str


@dataclass(frozen=True)
class Table:
    """The measured table: ``cells[method][property]``."""
    cells: dict[str, dict[str, Cell]]
    tol: float
    trials: int
    seed: int
    seconds: float = 0.0
    reference: Mapping[str, Mapping[str, bool]] = field(default_factory=lambda: PAPER)

    @property
    def methods(self) -> list[str]:
        return list(self.cells)

    def expected(self, method: str, prop: str) -> bool | None:
        return self.reference.get(prop, {}).get(method)

    def mismatches(self) -> list[tuple[str, str]]:
        """``(method, property)`` of every cell that disagrees with the reference (methods the
        reference does not know are not compared)."""
        return [(m, p) for m, row in self.cells.items() for p, c in row.items()
                if self.expected(m, p) is not None and self.expected(m, p) != c.holds]


# ---- random and adversarial inputs ----------------------------------------------------------

def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _axis_angle_quat(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    h = np.asarray(angle)[..., None] / 2
    return np.concatenate([np.cos(h), np.sin(h) * _unit(axis)], axis=-1)


def _random_poses(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    # Gaussian 4-vectors normalised are uniform on SO(3); translations of order 1 m.
    return dq.from_pose(_unit(rng.normal(size=shape + (4,))), rng.normal(size=shape + (3,)))


def _random_weights(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    return rng.uniform(0.05, 1.0, size=shape)


def _blend_sets(rng: np.random.Generator, n: int, trials: int) -> tuple[np.ndarray, np.ndarray]:
    """``trials`` random sets of ``n`` poses with weights, then adversarial sets: rotations near
    pi, pure translations, all poses equal, inputs with random signs (q vs -q), zero weights."""
    k = max(trials // 8, 1)
    dqs = [_random_poses(rng, (trials, n))]
    w = [_random_weights(rng, (trials, n))]
    # rotations of 170-179.9 degrees, where the principal log and the hemisphere tests are busiest
    near_pi = dq.from_pose(_axis_angle_quat(rng.normal(size=(k, n, 3)),
                                            np.radians(rng.uniform(170.0, 179.9, (k, n)))),
                           rng.normal(size=(k, n, 3)))
    dqs.append(near_pi)
    w.append(_random_weights(rng, (k, n)))
    pure_t = dq.from_pose(np.broadcast_to([1.0, 0.0, 0.0, 0.0], (k, n, 4)),
                          rng.normal(size=(k, n, 3)))
    dqs.append(pure_t)
    w.append(_random_weights(rng, (k, n)))
    dqs.append(np.repeat(_random_poses(rng, (k, 1)), n, axis=1))
    w.append(_random_weights(rng, (k, n)))
    signs = np.where(rng.random((k, n, 1)) < 0.5, -1.0, 1.0)
    dqs.append(signs * _random_poses(rng, (k, n)))
    w.append(_random_weights(rng, (k, n)))
    sparse = _random_weights(rng, (k, n))
    sparse[:, 1:] *= rng.random((k, n - 1)) < 0.5  # weight 0 on some poses, never on all
    dqs.append(_random_poses(rng, (k, n)))
    w.append(sparse)
    return np.concatenate(dqs), np.concatenate(w)


def _pairs(rng: np.random.Generator, trials: int) -> tuple[np.ndarray, list[str]]:
    """Pose pairs ``(P, 2, 8)`` for the path properties, with a label per pair.

    The random pairs are built from their relative screw so that every pair has a substantial
    rotation (60-170 deg) and translation along the axis (0.2-1.5 m): there a method without
    constant speed shows it by orders of magnitude over rounding."""
    M0 = _random_poses(rng, (trials,))
    s = _unit(rng.normal(size=(trials, 3)))
    theta = np.radians(rng.uniform(60.0, 170.0, trials))
    d = rng.uniform(0.2, 1.5, trials) * np.where(rng.random(trials) < 0.5, -1.0, 1.0)
    p = rng.normal(size=(trials, 3))  # a point on the screw axis
    m = np.cross(p, s)
    half_twist = np.concatenate([theta[:, None] / 2 * s,
                                 d[:, None] / 2 * s + theta[:, None] / 2 * m], axis=1)
    M1 = dq.mul(M0, dq.exp(half_twist))
    pairs = [np.stack([M0, M1], axis=1)]
    labels = ["random"] * trials

    # +170 and -170 deg about one axis: the short way is 20 deg, the long way (what the principal
    # logs blend linearly) 340 deg. Translations chosen with >= 0.2 m along the axis.
    k = max(trials // 4, 2)
    u = _unit(rng.normal(size=(k, 3)))
    t0 = rng.normal(size=(k, 3))
    along = rng.uniform(0.2, 1.5, k) * np.where(rng.random(k) < 0.5, -1.0, 1.0)
    t1 = t0 + rng.normal(size=(k, 3))
    t1 += (along - np.einsum("ij,ij->i", t1 - t0, u))[:, None] * u
    a0 = dq.from_pose(_axis_angle_quat(u, np.full(k, np.radians(170.0))), t0)
    a1 = dq.from_pose(_axis_angle_quat(u, np.full(k, np.radians(-170.0))), t1)
    pairs.append(np.stack([a0, a1], axis=1))
    labels += ["+-170deg"] * k

    # q versus -q: the same poses as the first random pairs with one or both signs flipped.
    j = min(k, trials)
    flips = np.array([[1.0, -1.0], [-1.0, 1.0], [-1.0, -1.0]])[np.arange(j) % 3]
    pairs.append(pairs[0][:j] * flips[:, :, None])
    labels += ["q vs -q"] * j
    return np.concatenate(pairs), labels


# ---- measurements ---------------------------------------------------------------------------

def _rigidity_dev(M: np.ndarray) -> np.ndarray:
    """Per matrix: the largest of |R^T R - I|, |det R - 1| and the bottom row's error."""
    R = M[..., :3, :3]
    orth = np.abs(np.swapaxes(R, -1, -2) @ R - np.eye(3)).max(axis=(-1, -2))
    det = np.abs(np.linalg.det(R) - 1.0)
    bottom = np.abs(M[..., 3, :] - [0.0, 0.0, 0.0, 1.0]).max(axis=-1)
    return np.maximum(np.maximum(orth, det), bottom)


def _rigid_inv(M: np.ndarray) -> np.ndarray:
    R, t = M[..., :3, :3], M[..., :3, 3]
    out = np.zeros_like(M)
    out[..., :3, :3] = np.swapaxes(R, -1, -2)
    out[..., :3, 3] = -np.einsum("...ji,...j->...i", R, t)
    out[..., 3, 3] = 1.0
    return out


def _max(x) -> float:
    x = np.asarray(x, dtype=float)
    return float(np.max(x)) if x.size else 0.0


def _accepts_many(method: Method, rng: np.random.Generator) -> tuple[bool, str]:
    """Does the method take n > 2 poses? Probed before the other properties so they can feed it
    the largest sets it accepts."""
    try:
        method(_random_poses(rng, (3,)), _random_weights(rng, (3,)))
    except ValueError as exc:
        return False, str(exc)
    return True, ""


def _measure_many(method: Method, rng: np.random.Generator, trials: int, tol: float) -> Cell:
    accepted, why = _accepts_many(method, rng)
    if not accepted:
        return Cell(False, float("nan"), f"rejects 3 poses: ValueError: {why}")
    worst = 0.0
    for n in range(3, 9):
        # A result is not enough: blending n copies of one pose must give that pose, and any set
        # must give finite numbers.
        k = max(trials // 6, 1)
        p = _random_poses(rng, (k,))
        same = method(np.repeat(p[:, None], n, axis=1), _random_weights(rng, (k, n)))
        worst = max(worst, _max(np.abs(same - dq.to_matrix(p))))
        dqs, w = _blend_sets(rng, n, k)
        M = method(dqs, w)
        if not np.all(np.isfinite(M)):
            return Cell(False, float("inf"), f"non-finite result for n = {n}")
    return Cell(worst <= tol, worst,
                f"accepts n = 3..8; blending n copies of a pose returns it within {worst:.1e}")


def _sets_for(method: Method, many: bool, rng: np.random.Generator, trials: int):
    """Input sets for the blend properties: n = 2 always, n = 3..6 where the method takes them."""
    ns = (2, 3, 4, 5, 6) if many else (2,)
    per = max(trials // len(ns), 1)
    return [_blend_sets(rng, n, per) for n in ns]


def _measure_rigidity(method, sets, tol) -> Cell:
    worst = max(_max(_rigidity_dev(method(dqs, w))) for dqs, w in sets)
    return Cell(worst <= tol, worst,
                f"worst |R^T R - I|, |det R - 1| over random blends: {worst:.1e}")


def _measure_bi_invariance(method, sets, rng, tol) -> Cell:
    left = right = 0.0
    for dqs, w in sets:
        r = _random_poses(rng, (len(dqs),))
        Mr = dq.to_matrix(r)
        B = method(dqs, w)
        left = max(left, _max(np.abs(method(dq.mul(r[:, None], dqs), w) - Mr @ B)))
        right = max(right, _max(np.abs(method(dq.mul(dqs, r[:, None]), w) - B @ Mr)))
    worst = max(left, right)
    return Cell(worst <= tol, worst, f"|blend(r q) - r blend(q)| = {left:.1e}, "
                                     f"|blend(q r) - blend(q) r| = {right:.1e}")


def _measure_coordinate_invariance(method, sets, rng, tol) -> Cell:
    worst = 0.0
    for dqs, w in sets:
        T = _random_poses(rng, (len(dqs),))
        conj_in = dq.mul(dq.mul(T[:, None], dqs), dq.conj(T)[:, None])
        MT = dq.to_matrix(T)
        worst = max(worst, _max(np.abs(method(conj_in, w) - MT @ method(dqs, w) @ _rigid_inv(MT))))
    return Cell(worst <= tol, worst, f"|blend(T q T^-1) - T blend(q) T^-1| = {worst:.1e}")


@dataclass(frozen=True)
class _Paths:
    """What the path properties need, measured once for both."""
    rigid_dev: float           # worst rigidity deviation of Phi(t) (and endpoint error)
    speed_dev: np.ndarray      # per pair: relative deviation of alpha' and delta' from constant
    axis_dev: np.ndarray       # per pair: largest angle between a(t) and a(1), rad
    dir_dev: np.ndarray        # per pair: largest angle between d(t) and d(1), rad
    swept: np.ndarray          # per pair: rotation swept along the path, rad
    labels: list[str]


def _path_measurements(method: Method, pairs: np.ndarray, labels: list[str]) -> _Paths:
    P, N = len(pairs), PATH_SAMPLES
    t = np.linspace(0.0, 1.0, N + 1)
    dqs = np.broadcast_to(pairs[:, None], (P, N + 1, 2, 8))
    w = np.broadcast_to(np.stack([1.0 - t, t], axis=1), (P, N + 1, 2))
    Phi = method(dqs, w)  # (P, N+1, 4, 4)
    ends = dq.to_matrix(pairs)
    # A valid interpolation passes through M0 and M1 and is rigid everywhere.
    rigid = max(_max(_rigidity_dev(Phi)), _max(np.abs(Phi[:, 0] - ends[:, 0])),
                _max(np.abs(Phi[:, -1] - ends[:, 1])))
    if not rigid <= 1e-6:  # dq.from_matrix below refuses anything further off
        nan = np.full(P, np.nan)
        return _Paths(rigid, nan, nan, nan, nan, labels)

    rel = dq.screw(dq.from_matrix(_rigid_inv(ends[:, :1]) @ Phi))  # M0^-1 Phi(t)
    theta, d, axis = rel.theta, rel.d, rel.axis

    # dq.screw gives the angle in [0, pi] with its axis, so a path through pi shows up as the
    # axis flipping and the angle folding back. Orient the axis by continuity along the path
    # (t = 0 has no axis: it is the identity) and carry alpha and delta with that orientation,
    # then unwrap alpha: that is the alpha(t) of the paper, free of the [0, pi] convention.
    sign = np.ones_like(theta)
    for k in range(2, N + 1):
        prev = axis[:, k - 1] * sign[:, k - 1, None]
        sign[:, k] = np.where(np.einsum("ij,ij->i", axis[:, k], prev) < 0.0, -1.0, 1.0)
    alpha = np.unwrap(theta * sign, axis=1)
    delta = d * sign

    # Constant derivative <=> equal steps. Each step is compared with the mean step, relative to
    # the mean speed but never below 1 rad (1 m) per unit t: below that the DIB/Dec stopping
    # error (1e-12) divided by a near-zero speed would read as a speed change.
    def speed_variation(x):
        steps = np.diff(x, axis=1)
        mean = (x[:, -1] - x[:, 0]) / N
        scale = np.maximum(np.abs(x[:, -1] - x[:, 0]), 1.0) / N
        return np.abs(steps - mean[:, None]).max(axis=1) / scale
    speed_dev = np.maximum(speed_variation(alpha), speed_variation(delta))

    # Shortest path: the axis is compared as a direction without sign (a rotation by pi about a
    # and about -a is the same), the translation along it as a signed vector d(t) delta(t).
    # Angles from atan2(|u x v|, u.v): arccos of a dot product near 1 loses half the digits.
    def angle(u, v, signed):
        cos = np.einsum("...i,...i->...", u, v)
        return np.arctan2(np.linalg.norm(np.cross(u, v), axis=-1), cos if signed else np.abs(cos))
    axis_dev = angle(axis[:, 1:], axis[:, -1:], signed=False).max(axis=1)
    vec = d[..., None] * axis  # translation along the screw axis, independent of the axis sign
    norm = np.linalg.norm(vec, axis=-1)
    resolvable = (norm[:, 1:] > 1e-6) & (norm[:, -1:] > 1e-6)  # a direction needs a length
    dir_dev = np.where(resolvable, angle(vec[:, 1:], vec[:, -1:], signed=True), 0.0).max(axis=1)
    # The rotation swept: the sum of the rotation angles between consecutive samples, so a path
    # that goes the long way round counts its full length even though alpha(1) folds to [0, pi].
    step = dq.screw(dq.from_matrix(_rigid_inv(Phi[:, :-1]) @ Phi[:, 1:]))
    swept = step.theta.sum(axis=1)
    return _Paths(rigid, speed_dev, axis_dev, dir_dev, swept, labels)


def _worst_by_label(dev: np.ndarray, labels: list[str]) -> str:
    lab = np.asarray(labels)
    return ", ".join(f"{name} {np.max(dev[lab == name]):.1e}" for name in dict.fromkeys(labels))


def _not_rigid_cell(paths: _Paths) -> Cell:
    return Cell(False, paths.rigid_dev,
                f"Phi(t) is not a rigid interpolant (deviation {paths.rigid_dev:.1e}); the "
                "definition assumes one, so the property does not hold")


def _measure_constant_speed(paths: _Paths, tol: float) -> Cell:
    if not paths.rigid_dev <= tol:
        return _not_rigid_cell(paths)
    worst = _max(paths.speed_dev)
    return Cell(worst <= tol, worst, "max |step - mean step| / mean step of alpha and delta: "
                + _worst_by_label(paths.speed_dev, paths.labels))


def _measure_shortest(paths: _Paths, tol: float) -> Cell:
    if not paths.rigid_dev <= tol:
        return _not_rigid_cell(paths)
    excess = np.maximum(paths.swept - np.pi, 0.0)
    dev = np.maximum(np.maximum(paths.axis_dev, paths.dir_dev), excess)
    worst = _max(dev)
    return Cell(worst <= tol, worst,
                f"axis moves {_max(paths.axis_dev):.1e} rad, translation direction "
                f"{_max(paths.dir_dev):.1e} rad, swept up to "
                f"{np.degrees(_max(paths.swept)):.1f} deg"
                f" (per input kind: {_worst_by_label(dev, paths.labels)})")


def measure_method(method: Method, rng: np.random.Generator, trials: int = 200,
                   tol: float = DEFAULT_TOL) -> dict[str, Cell]:
    """All six properties of one method (any callable with the :data:`Method` signature)."""
    many, _ = _accepts_many(method, rng)
    sets = _sets_for(method, many, rng, trials)
    pairs, labels = _pairs(rng, max(trials // 4, 8))
    paths = _path_measurements(method, pairs, labels)
    return {
        "rigidity": _measure_rigidity(method, sets, tol),
        "bi-inv": _measure_bi_invariance(method, sets, rng, tol),
        "coord-inv": _measure_coordinate_invariance(method, sets, rng, tol),
        "n>2": _measure_many(method, rng, trials, tol),
        "const-speed": _measure_constant_speed(paths, tol),
        "shortest": _measure_shortest(paths, tol),
    }


def measure(trials: int = 200, seed: int = 0, tol: float = DEFAULT_TOL,
            methods: Mapping[str, Method] | None = None, progress: bool = False) -> Table:
    """Measure every property of every method. Each method draws from its own stream, seeded by
    ``seed`` and its name, so its cells do not depend on which other methods are measured."""
    if isinstance(trials, bool) or int(trials) != trials or trials < 8:
        raise ValueError(f"trials: must be a whole number >= 8, got {trials!r}")
    if not (tol > 0.0):
        raise ValueError(f"tol: must be positive, got {tol!r}")
    methods = METHODS if methods is None else methods
    start = time.perf_counter()
    cells = {}
    items: Iterable[tuple[str, Method]] = methods.items()
    if progress:
        from tqdm import tqdm  # only here: the default run takes a fraction of a second
        items = tqdm(items, desc="measuring", unit="method", leave=False)
    for name, method in items:
        rng = np.random.default_rng([seed, zlib.crc32(name.encode())])
        cells[name] = measure_method(method, rng, int(trials), tol)
    return Table(cells, tol, int(trials), seed, time.perf_counter() - start)


# ---- output and command line ----------------------------------------------------------------

def _sym(b: bool) -> str:
    return "+" if b else "-"


def format_table(table: Table, verbose: bool = False) -> str:
    """The measured table, one row per property: ``+``/``-``, the worst deviation, and the paper's
    value in brackets; ``!`` marks a cell that disagrees with the paper. ``verbose`` adds each
    cell's reason."""
    width = 18
    lines = [
        f"Table 1 of Kavan et al., measured on dqpose (seed {table.seed}, {table.trials} trials, "
        f"tol {table.tol:.0e}, {table.seconds:.2f} s)",
        "cell: measured, worst deviation, [paper]; '!' marks a disagreement with the paper",
        "",
        ("property     " + "".join(f"{m:<{width}}" for m in table.methods)).rstrip(),
    ]
    for prop in PROPERTIES:
        row = f"{prop:<13}"
        for m in table.methods:
            c = table.cells[m][prop]
            ref = table.expected(m, prop)
            worst = f"{c.worst:.1e}" if np.isfinite(c.worst) else "n/a"
            mark = "" if ref is None else f"[{_sym(ref)}]" + ("!" if ref != c.holds else "")
            row += f"{_sym(c.holds)} {worst:<8} {mark:<{width - 11}}"
        lines.append(row.rstrip())
    bad = table.mismatches()
    compared = sum(table.expected(m, p) is not None for m in table.methods for p in PROPERTIES)
    lines.append("")
    if compared:
        lines.append(f"{compared - len(bad)}/{compared} cells agree with the paper"
                     + ("." if not bad
                        else ": disagree at " + ", ".join(f"{m} {p}" for m, p in bad)))
    else:
        lines.append("The paper has no column for these methods.")
    if verbose:
        lines.append("")
        name = max(len(m) for m in table.methods)
        for m in table.methods:
            for prop in PROPERTIES:
                c = table.cells[m][prop]
                lines.append(f"{m:<{name}} {prop:<12} {_sym(c.holds)}  {c.reason}")
    return "\n".join(lines)
