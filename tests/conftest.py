"""Shared test fixtures: a seeded RNG, random unit dual quaternions, the hypothesis profile."""
from __future__ import annotations

import os
import sys
import zlib

import numpy as np
import pytest
from hypothesis import HealthCheck, settings

# reference.py sits next to the tests; make it importable however pytest was started.
sys.path.insert(0, os.path.dirname(__file__))

import reference  # noqa: E402

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


#: the modules whose tests take the most time (arms, servers and simulators on the clock, the
#: hand-eye solves, the fuzz): ``make test-fast`` leaves them out, ``make test`` (CI) runs all
SLOW_MODULES = {
    "test_fuzz_rpc.py", "test_demo_fusion.py", "test_fusion_time.py", "test_handeye_cli.py",
    "test_handeye.py", "test_execute.py", "test_bench_handeye.py", "test_handeye_capture.py",
    "test_bench_handeye_kinhec.py", "test_readings.py",
    "test_server.py", "test_armproc_respawn.py", "test_arm_safety.py", "test_examples.py",
    "test_interrupt.py", "test_camera.py",
}


def pytest_collection_modifyitems(items):
    for item in items:
        if item.path.name in SLOW_MODULES:
            item.add_marker(pytest.mark.slow)
