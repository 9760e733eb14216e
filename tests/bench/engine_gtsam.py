"""The GTSAM 4.3 side of bench_engine: the scene of ../shared/notes/world-engine-frames.md as a
factor graph. A body is one ``Pose3`` key per 30 Hz tick; each camera measurement is a
``PriorFactorPose3`` on its nearest key with the measurement's noise (an uncertain camera's, a
``BetweenFactorPose3`` from the mount's ``Pose3`` variable, which has its own prior); consecutive
keys are joined by a ``BetweenFactorPose3`` of the identity (a random walk of :data:`WALK` a
tick: GTSAM's model has no twist). Default ``ISAM2Params``. What is timed is what an answer with a
covariance costs: the update, the estimate and the marginal (or joint marginal) covariance; the
factors are built before, untimed. Import only where ``gtsam`` is installed."""
from __future__ import annotations

import time

import gtsam
import numpy as np

from dqpose import dq

#: the random walk between consecutive 30 Hz keys: 0.5° and 5 mm a tick (1 σ)
WALK = np.r_[np.full(3, np.deg2rad(0.5)), np.full(3, 5e-3)]


def pose3(q) -> gtsam.Pose3:
    return gtsam.Pose3(dq.to_matrix(q))


def dq_of(p: gtsam.Pose3) -> np.ndarray:
    return dq.from_matrix(p.matrix())


def noise(cov) -> gtsam.noiseModel.Base:
    """A covariance's noise model (``smart=False``: GTSAM's default would drop off-diagonal
    entries below 1e-9 of a tiny covariance, tests/_gtsam.py)."""
    return gtsam.noiseModel.Gaussian.Covariance(np.asarray(cov, dtype=float), False)


class Chain:
    """One body's keys (``letter`` and the tick's number) and what a tick adds to a graph: the
    key, the walk from the key before, the tick's measurements on their nearest key, each
    ``(time, pose in the world, covariance)`` or ``(time, pose in the mount's frame, covariance,
    mount key)``."""

    def __init__(self, letter: str, rate: float = 30.0):
        self.letter, self.rate = letter, rate
        self.walk = gtsam.noiseModel.Diagonal.Sigmas(WALK)
        self.newest: int | None = None              # the newest key's tick
        self.last: gtsam.Pose3 | None = None        # and its estimate, the next key's start

    def key(self, k: int) -> int:
        return gtsam.symbol(self.letter, k)

    def add(self, k: int, measured, graph, values) -> None:
        """Key ``k`` and the factors of ``measured`` (taken after tick ``k - 1``, each on its
        nearest key: ``k - 1`` or ``k``) into ``graph`` and ``values``."""
        for m in measured:
            t, z, cov = m[:3]
            near = int(round(t * self.rate))
            key = self.key(near if self.newest is not None and near <= self.newest else k)
            if len(m) == 4:
                graph.add(gtsam.BetweenFactorPose3(m[3], key, pose3(z), noise(cov)))
            else:
                graph.add(gtsam.PriorFactorPose3(key, pose3(z), noise(cov)))
        if self.newest is not None:
            graph.add(gtsam.BetweenFactorPose3(self.key(self.newest), self.key(k), gtsam.Pose3(),
                                               self.walk))
        # the first key starts at a measurement in the world frame (a scene has one)
        start = self.last if self.last is not None else next(
            pose3(m[1]) for m in measured if len(m) == 3)
        values.insert(self.key(k), start)
        self.newest = k


class Tick:
    """One body's ticks on an ``IncrementalFixedLagSmoother`` (``lag`` s) or on ``ISAM2``
    (``lag`` None). :meth:`tick` adds tick ``k``'s factors (untimed) and times the update, the
    newest key's estimate and its marginal covariance: ``(CPU s, wall s, pose, covariance)``."""

    def __init__(self, lag: float | None, rate: float = 30.0):
        self.lag, self.rate = lag, rate
        self.solver = (gtsam.ISAM2() if lag is None else
                       gtsam.IncrementalFixedLagSmoother(lag, gtsam.ISAM2Params()))
        self.chain = Chain("x", rate)

    def tick(self, k: int, measured) -> tuple[float, float, np.ndarray, np.ndarray]:
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        self.chain.add(k, measured, graph, values)
        key = self.chain.key(k)
        stamps = {key: k / self.rate}
        s = self.solver
        c0, t0 = time.thread_time(), time.perf_counter()
        if self.lag is None:
            s.update(graph, values)
        else:
            s.update(graph, values, stamps)
        est = s.calculateEstimatePose3(key)
        cov = s.marginalCovariance(key)
        cpu, wall = time.thread_time() - c0, time.perf_counter() - t0
        self.chain.last = est
        return cpu, wall, dq_of(est), cov


class Pair:
    """Two bodies ``a`` and ``b`` on one ``IncrementalFixedLagSmoother`` (``lag`` s; its ISAM2
    answers the joint marginal), optionally with a mount (key ``m``, its prior ``mount`` =
    (pose, covariance), kept in the lag) that the uncertain camera's measurements hang from.
    :meth:`tick` adds tick ``k``'s factors and times the update, both newest keys' estimates and
    their joint marginal covariance: ``(CPU s, wall s, T_a_b, joint covariance 12×12)``."""

    def __init__(self, lag: float, mount=None, rate: float = 30.0):
        self.solver = gtsam.IncrementalFixedLagSmoother(lag, gtsam.ISAM2Params())
        self.rate = rate
        self.chains = {b: Chain(b, rate) for b in "ab"}
        self.mount_key = gtsam.symbol("m", 0)
        self.mount, self.mounted = mount, mount is not None

    def tick(self, k: int, measured: dict) -> tuple[float, float, np.ndarray, np.ndarray]:
        """``measured``: per body its tick's measurements (:class:`Chain`'s forms; an uncertain
        camera's name the mount by ``"m"`` in their fourth place)."""
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        stamps = {}
        if self.mount is not None:
            pose, cov = self.mount
            graph.add(gtsam.PriorFactorPose3(self.mount_key, pose3(pose), noise(cov)))
            values.insert(self.mount_key, pose3(pose))
            self.mount = None
        if self.mounted:
            stamps[self.mount_key] = k / self.rate      # stamped anew: never marginalised
        for b, chain in self.chains.items():
            chain.add(k, [m[:3] + (self.mount_key,) if len(m) == 4 else m
                          for m in measured[b]], graph, values)
            stamps[chain.key(k)] = k / self.rate
        ka, kb = (c.key(k) for c in self.chains.values())
        s = self.solver
        c0, t0 = time.thread_time(), time.perf_counter()
        s.update(graph, values, stamps)
        xa, xb = s.calculateEstimatePose3(ka), s.calculateEstimatePose3(kb)
        joint = s.getISAM2().jointMarginalCovariance([ka, kb]).fullMatrix()
        cpu, wall = time.thread_time() - c0, time.perf_counter() - t0
        self.chains["a"].last, self.chains["b"].last = xa, xb
        return cpu, wall, dq_of(xa.between(xb)), joint
