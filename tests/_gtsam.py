"""GTSAM as the reference for pose fusion (tests and the fusion benchmark): one prior factor per
measurement, Levenberg-Marquardt, the marginal. Import only where ``gtsam`` is installed."""
import gtsam
import numpy as np

from dqpose import dq


def priors(Z, S, start=None):
    """``PriorFactorPose3(0, Z_i, Σ_i)`` for every measurement, the pose started at ``start``
    (the first measurement when None)."""
    # smart=False: GTSAM's default takes a covariance whose off-diagonal entries are all below
    # 1e-9 in absolute value for a diagonal one and drops them (a tiny covariance loses its
    # correlations).
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    for z, s in zip(Z, S):
        graph.add(gtsam.PriorFactorPose3(0, gtsam.Pose3(dq.to_matrix(z)),
                                         gtsam.noiseModel.Gaussian.Covariance(s, False)))
    values.insert(0, gtsam.Pose3(dq.to_matrix(Z[0] if start is None else start)))
    return graph, values


def lm(graph, values):
    """What a GTSAM user runs: Levenberg-Marquardt with tolerances at float64's limit."""
    p = gtsam.LevenbergMarquardtParams()
    p.setRelativeErrorTol(1e-16)
    p.setAbsoluteErrorTol(1e-16)
    p.setMaxIterations(500)
    return gtsam.LevenbergMarquardtOptimizer(graph, values, p).optimize()


def finish(graph, result):
    """GTSAM's optimum. LM (and GTSAM's Gauss-Newton optimizer) stop when the error stops
    decreasing in float64, which on these flat optima leaves the pose up to ~1e-8 rad off (its
    gradient is not zero there). GTSAM's own linearisation and step, iterated until the step is
    below 1e-13, finish it."""
    for _ in range(200):
        delta = graph.linearize(result).optimize()
        result = result.retract(delta)
        if np.linalg.norm(delta.at(0)) < 1e-13:
            break
    return result


def pose(result) -> np.ndarray:
    return dq.from_matrix(result.atPose3(0).matrix())


def marginal(graph, result) -> np.ndarray:
    return gtsam.Marginals(graph, result).marginalCovariance(0)
