"""HandEye Calibrate against the probe's requests: pairs and corners within stated limits,
refused before any work beyond them, the heaviest legal request solved off the event loop with
the server answering meanwhile and its memory given back."""
from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import grpc
import numpy as np
import pytest

from dqpose import limits
from dqpose.rpc import handeye_convert
from dqpose.rpc._proto.dqpose.v1 import handeye_pb2_grpc as pb_grpc
from tests import _handeye as H
from tests.robustness._served import code_of, served


@pytest.fixture(scope="module")
def server():
    with served() as s:
        yield s


def request(n, corners=False, seed=1, squares=None):
    """``n`` pairs of a wrist scene, with each view's corners (``squares`` of a larger board
    than the 7 x 5 one when given)."""
    s = H.scene(n, seed=seed)
    cs = None
    if squares:
        cs = H.exact_corners(s, squares)
    elif corners:
        cs = H.corners(s)
    return handeye_convert.calibrate_msg(s.base_flange, s.camera_target, s.setup, corners=cs)


def calibrate(server, req, timeout=120.0):
    return pb_grpc.HandEyeStub(server.channel).Calibrate(req, timeout=timeout)


def test_the_probes_ten_thousand_pairs_are_refused_naming_the_limit(server):
    code, details = code_of(lambda: calibrate(server, request(10_000), timeout=60))
    assert code == grpc.StatusCode.RESOURCE_EXHAUSTED, (code, details)
    assert details.startswith("pairs: 10000 pairs, over the server's limit max_pairs = "), details
    assert "--max-pairs" in details
    assert server.health() == "SERVING"


def test_corners_over_the_limit_are_refused_naming_it(server):
    n = limits.DEFAULT.max_corners // 99 + 1        # 99 corners a view
    code, details = code_of(lambda: calibrate(server, request(n, squares=(12, 10))))
    assert code == grpc.StatusCode.RESOURCE_EXHAUSTED, (code, details)
    assert details.startswith(f"pairs: {99 * n} corners in all"), details
    assert "max_corners" in details and "--max-corners" in details


@pytest.mark.heavy
def test_the_largest_calibration_leaves_the_server_answering_and_memory_returns(server):
    n = limits.DEFAULT.max_pairs
    calibrate(server, request(10))
    baseline = server.rss_mb()
    req = request(n, corners=True)          # 4,800 corners: the probe's 1,000 pairs took 1.2 GB
    with ThreadPoolExecutor(3) as pool:
        calls = [pool.submit(calibrate, server, req, 600) for _ in range(3)]
        assert server.health() == "SERVING"     # while they run
        answers = [c.result() for c in calls]
    truth = H.scene(n, seed=1)
    for a in answers:
        x = handeye_convert.calibration_from_msg(a, "eye_in_hand").x
        assert H.pose_error(x, truth.x)[1] < 1.0      # mm: solved, not refused
    assert server.rss_mb() < baseline + 150, (baseline, server.rss_mb())


# ---- D4: a covariance's error names that covariance

def test_a_robot_covariance_of_1e30_is_named_as_the_robot_covariance(server):
    s = H.scene(10, seed=1)
    req = handeye_convert.calibrate_msg(s.base_flange, s.camera_target, s.setup,
                                camera_covariance=s.camera_covariance,
                                robot_covariance=np.diag([1e30, 0, 0, 0, 0, 0]))
    code, details = code_of(lambda: calibrate(server, req))
    assert code == grpc.StatusCode.INVALID_ARGUMENT, (code, details)
    assert details.startswith("pairs[0].robot_covariance: variance 1e+30 outside"), details


def test_a_singular_residual_covariance_names_the_sample_and_both_covariances(server):
    s = H.scene(10, seed=1)
    camera = np.broadcast_to(s.camera_covariance, (10, 6, 6)).copy()
    camera[4] = np.diag([1e-6, 0, 1e-6, 1e-6, 1e-6, 1e-6])
    req = handeye_convert.calibrate_msg(s.base_flange, s.camera_target, s.setup,
                                camera_covariance=camera, robot_covariance=np.zeros((6, 6)))
    code, details = code_of(lambda: calibrate(server, req))
    assert code == grpc.StatusCode.INVALID_ARGUMENT, (code, details)
    assert details.startswith("pairs[4].camera_covariance, pairs[4].robot_covariance: the "
                              "residual covariance of this sample"), details
