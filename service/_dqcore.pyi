# The C core (service/csrc/, module.c's method table), for type checkers: its functions take and
# return NumPy arrays; their signatures are documented where dqpose.dq and the others wrap them.
from typing import Any

def __getattr__(name: str) -> Any: ...

# service/csrc/py_joint.c (joint.h): one problem a call, part j the next counts[j] measurements;
# -> (X, V, L, Ehat, H, P, g, dt, residuals, cost, G | None, nis | None, tested | None, chi2,
# status, iterations).
def joint_fit(poses: Any, covariances: Any, inliers: Any, counts: Any, stamps: Any,
              latencies: Any, latency_slots: Any, extrinsic_slots: Any, starts: Any,
              twists: Any, twist_flags: Any, twist_information: Any, twist_priors: Any,
              latency_starts: Any, priors: Any, prior_information: Any, extrinsics: Any,
              extrinsic_information: Any, nis: bool = ..., tol: float = ..., max_iter: int = ...,
              jacobians: bool = ..., /) -> tuple[Any, ...]: ...
