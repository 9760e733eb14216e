"""Moving-body scenes over time: two cameras and an arm with latencies, a body on a constant or
accelerating twist, and their measurements."""
import numpy as np

from dqpose import dq, lie
from dqpose.fusion import Measurement, Source

CAMERA_RATE, ARM_RATE = 30.0, 500.0


LATENCY = 0.04          # the cameras'; the arm's is 4 ms


ARM_LATENCY = 0.004


WINDOW = 0.2


TWIST = np.array([0.3, -0.2, 0.5, 0.2, 0.1, -0.15])   # rad/s, m/s: 8 mm in the cameras' 40 ms


ACCELERATION = np.array([0.1, 0.05, -0.08, 0.05, -0.03, 0.04])  # rad/s², m/s²: "mildly"


def deg(x):
    return np.deg2rad(x)


# Anisotropic, correlated sources of comparable quality: cameras good across the image, poor in
# depth (each looking along its own axis), an arm with millimetre noise.
def _rotated(C, axis_angle):
    R = np.eye(6)
    R[:3, :3] = R[3:, 3:] = dq.to_matrix(lie.se3_exp(np.r_[axis_angle, 0, 0, 0]))[:3, :3]
    return R @ C @ R.T


CAM_A = _rotated(np.diag([deg(0.15) ** 2] * 3 + [0.5e-3 ** 2, 0.5e-3 ** 2, 3e-3 ** 2]),
                 [0.0, 0.0, 0.0])


CAM_B = _rotated(np.diag([deg(0.2) ** 2] * 3 + [0.6e-3 ** 2, 0.6e-3 ** 2, 4e-3 ** 2]),
                 [1.2, 0.3, 0.0])


ARM = np.diag([deg(0.5) ** 2] * 3 + [2e-3 ** 2] * 3)


SOURCES = [Source("cam_a", latency=LATENCY), Source("cam_b", latency=LATENCY),
           Source("arm", latency=ARM_LATENCY)]


def trajectory(X0, accelerating):
    """Constant twist ``T(t) = X0 Exp(t V)``, or ``X0 Exp(t V + t²/2 a)``."""
    def T(t):
        t = np.atleast_1d(np.asarray(t, dtype=float))
        xi = t[:, None] * TWIST + (0.5 * t[:, None] ** 2 * ACCELERATION if accelerating else 0.0)
        return dq.mul(X0, lie.se3_exp(xi))
    return T


def sample(rng, T, C, taken):
    """Poses ``T(τ) Exp(-ξ)``, ``ξ ~ N(0, C)``: the truth is ``Z Exp(ξ)`` (the convention)."""
    xi = rng.multivariate_normal(np.zeros(6), C, size=taken.size)
    return dq.mul(T(taken), lie.se3_exp(-xi))


def scene(rng, accelerating=False, end=1.0, window=WINDOW):
    """One window of measurements ending at ``end`` (stamp time): poses, covariances, source
    names, stamps, and the truth as a function of the time a pose was taken."""
    T = trajectory(lie.se3_exp(rng.normal(size=6)), accelerating)
    parts = []
    for name, rate, C, latency in (("cam_a", CAMERA_RATE, CAM_A, LATENCY),
                                   ("cam_b", CAMERA_RATE, CAM_B, LATENCY),
                                   ("arm", ARM_RATE, ARM, ARM_LATENCY)):
        stamps = end - np.arange(0.0, window, 1.0 / rate) - rng.uniform(0.0, 1.0 / rate)
        stamps = np.sort(stamps)
        parts.append((sample(rng, T, C, stamps - latency), np.broadcast_to(C, (stamps.size, 6, 6)),
                      [name] * stamps.size, stamps))
    Z = np.concatenate([p[0] for p in parts])
    S = np.concatenate([p[1] for p in parts])
    names = sum((p[2] for p in parts), [])
    stamps = np.concatenate([p[3] for p in parts])
    return Z, S, names, stamps, T


def error(X_hat, X):
    return lie.se3_log(dq.mul(dq.conj(X_hat), X))


def sizes(e):
    """Rotation angle (rad) and translation error (m) of twists ``e`` ``(..., 6)``."""
    return np.linalg.norm(e[..., :3], axis=-1), np.linalg.norm(e[..., 3:], axis=-1)


def subset(Z, S, names, stamps, keep):
    idx = [i for i, s in enumerate(names) if s in keep]
    return Z[idx], S[idx], [names[i] for i in idx], stamps[idx]


def naive(Z, names, stamps, source, latency, time):
    """A source alone, the plain way: its two newest poses, screw-extrapolated to ``time``."""
    idx = [i for i, s in enumerate(names) if s == source]
    idx = sorted(idx, key=lambda i: stamps[i])[-2:]
    (a, b), (ta, tb) = Z[idx], stamps[idx] - latency
    step = lie.se3_log(dq.mul(dq.conj(a), b))
    return dq.mul(b, lie.se3_exp((time - tb) / (tb - ta) * step))


def stream(rng, T, end=1.0, start=0.0, body="box", accelerating=False):
    """Measurements as they arrive (by stamp) from two cameras and the arm."""
    out = []
    for name, rate, C, latency in (("cam_a", CAMERA_RATE, CAM_A, LATENCY),
                                   ("cam_b", CAMERA_RATE, CAM_B, LATENCY),
                                   ("arm", ARM_RATE, ARM, ARM_LATENCY)):
        stamps = np.arange(start + rng.uniform(0, 1 / rate), end, 1 / rate)
        Z = sample(rng, T, C, stamps - latency)
        out += [Measurement(name, body, float(t), z, C) for t, z in zip(stamps, Z)]
    return sorted(out, key=lambda m: m.time)
