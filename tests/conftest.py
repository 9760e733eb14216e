"""Shared test fixtures: a seeded RNG, random unit dual quaternions, the hypothesis profile."""
from __future__ import annotations

import os
import pathlib
import zlib

import numpy as np
import pytest
from hypothesis import HealthCheck, settings

from tests import reference

# Deterministic by default so CI failures reproduce; HYPOTHESIS_PROFILE=dev explores more.
settings.register_profile("ci", max_examples=200, deadline=None, derandomize=True,
                          suppress_health_check=[HealthCheck.too_slow])
settings.register_profile("dev", max_examples=1000, deadline=None)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))


def _shape(shape) -> tuple[int, ...]:
    return (int(shape),) if np.ndim(shape) == 0 else tuple(int(k) for k in shape)


def random_quaternions(rng: np.random.Generator, shape=()) -> np.ndarray:
    """Uniformly distributed unit quaternions (..., 4), both signs."""
    q = rng.normal(size=_shape(shape) + (4,))
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def random_dqs(rng: np.random.Generator, shape=(), scale: float = 1.0) -> np.ndarray:
    """Random unit dual quaternions (..., 8): uniform rotations, translations ~ N(0, scale^2)."""
    shape = _shape(shape)
    r = random_quaternions(rng, shape)
    t = scale * rng.normal(size=shape + (3,))
    return reference.dq_from_rt(r, t)


@pytest.fixture
def rng(request) -> np.random.Generator:
    """A generator seeded from the test's name: reproducible and different for each test."""
    seed = zlib.crc32(request.node.nodeid.encode())
    return np.random.default_rng(seed)


@pytest.fixture
def make_dqs(rng):
    """``make_dqs(shape, scale=1.0)``: random unit dual quaternions from the test's RNG."""
    return lambda shape=(), scale=1.0: random_dqs(rng, shape, scale)


@pytest.fixture(scope="module")
def sim():
    """One simulated UR controller (its own process, a free 127.0.0.x) per test module.

    The lag tests measure the servo pipeline. On a loaded machine the simulator process itself
    may be descheduled and then read a burst of set-points at once; a generous speed limit keeps
    such bursts from being clipped (the speed limit has its own test)."""
    pytest.importorskip("rtde_control")
    from dqpose.drivers.sim import ur as ursim
    with ursim.URSimProcess(args=("--max-linear-speed", "5")) as s:
        yield s


#: the modules (paths under tests/) whose tests take the most time (arms, servers and simulators
#: on the clock, the hand-eye solves, the fuzz): ``make test-fast`` leaves them out, ``make test``
#: (CI) runs all
SLOW_MODULES = {
    "bench/test_bench_handeye.py", "bench/test_bench_handeye_kinhec.py",
    "bench/test_bench_world.py", "cli/test_demo_fusion.py",
    "cli/test_handeye_capture.py", "cli/test_handeye_cli.py", "cli/test_interrupt.py",
    "cli/test_world_cli.py", "cluster/test_proxies.py", "cluster/test_scale_out.py",
    "drivers/test_arm_safety.py",
    "drivers/test_armproc_respawn.py", "drivers/test_camera.py", "fusion/test_process_noise.py",
    "handeye/test_calibrate.py", "handeye/test_checks.py", "handeye/test_corners.py",
    "handeye/test_gate.py",
    "handeye/test_readings.py", "robustness/test_execute.py", "robustness/test_fuzz_rpc.py",
    "rpc/server/test_shutdown.py", "test_examples.py", "view/test_watch.py",
}
_TESTS = pathlib.Path(__file__).parent


def pytest_collection_modifyitems(items):
    for item in items:
        if item.path.relative_to(_TESTS).as_posix() in SLOW_MODULES:
            item.add_marker(pytest.mark.slow)
