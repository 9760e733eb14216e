"""The HandEye service on a real server on 127.0.0.1: Calibrate gives what dqpose.handeye gives in
process (both setups, estimated or given noise, outliers rejected), malformed requests are
INVALID_ARGUMENT naming the field, unusable data FAILED_PRECONDITION with the solver's reason
and samples, and the server goes on serving after each."""
from __future__ import annotations

import grpc
import numpy as np
import pytest

from dqpose import handeye
from dqpose.errors import Infeasible
from dqpose.rpc._proto.dqpose.v1 import handeye_pb2 as pb
from dqpose.rpc._proto.dqpose.v1 import handeye_pb2_grpc
from dqpose.rpc.client import Client, InvalidArgument, RpcError
from dqpose.rpc.handeye_convert import calibrate_error, calibrate_msg
from tests import _handeye
from tests.rpc._grpc_server import ServerThread


@pytest.fixture(scope="module")
def server():
    with ServerThread(max_poses=40) as s:
        yield s


@pytest.fixture
def client(server):
    with Client(server.target, max_poses=1000) as c:    # the server's limit is the one tested
        yield c


@pytest.fixture
def stub(server):
    with grpc.insecure_channel(server.target) as ch:
        yield handeye_pb2_grpc.HandEyeStub(ch)


def _same_pose(a, b, tol):
    a = a * np.sign(a[0] * b[0] + (a[0] * b[0] == 0))
    np.testing.assert_allclose(a, b, atol=tol, rtol=0)


def _assert_same(remote: handeye.Calibration, local: handeye.Calibration):
    # the poses travel as (q, t) and are dual quaternions again on the server: the same answer
    # up to the rounding of that conversion
    for name in ("x", "z", "closed_form_x", "closed_form_z"):
        _same_pose(getattr(remote, name), getattr(local, name), 1e-12)
    for name in ("covariance_x", "covariance_z", "covariance", "residuals", "leave_one_out",
                 "nis"):
        np.testing.assert_allclose(getattr(remote, name), getattr(local, name), rtol=1e-8,
                                   atol=0, err_msg=name)
    assert remote.warnings == local.warnings
    assert [(r.index, r.reason) for r in remote.rejected] == \
        [(r.index, r.reason) for r in local.rejected]
    np.testing.assert_array_equal(remote.inliers, local.inliers)
    assert remote.iterations == local.iterations and remote.noise_model == local.noise_model
    assert remote.agreement == pytest.approx(local.agreement, rel=1e-8)
    assert [r[0] for r in remote.readings] == [r[0] for r in local.readings]
    np.testing.assert_allclose(np.linalg.inv(remote.information), remote.covariance, rtol=1e-8)
    assert remote.camera_scale == pytest.approx(local.camera_scale, rel=1e-8)


@pytest.mark.parametrize("setup", handeye.SETUPS)
def test_calibrate_gives_what_the_domain_gives(client, setup):
    s = _handeye.scene(12, setup, camera_noise=(0.1, 0.5), seed=4)
    remote = client.calibrate(s.base_flange, s.camera_target, setup)
    local = handeye.calibrate(s.base_flange, s.camera_target, setup)
    assert remote.setup == setup
    _assert_same(remote, local)
    # and it is an answer: near the truth
    deg, mm = _handeye.pose_error(remote.x, s.x)
    assert deg < 0.5 and mm < 5.0


def test_duplicates_are_out_of_the_answer_on_both_sides(client):
    s = _handeye.scene(8, camera_noise=(0.1, 0.5), seed=6)
    F = np.concatenate([s.base_flange, s.base_flange[2:3]])      # pair 8: pair 2 again
    C = np.concatenate([s.camera_target, s.camera_target[2:3]])
    remote, local = client.calibrate(F, C), handeye.calibrate(F, C)
    _assert_same(remote, local)
    assert not remote.rejected and remote.inliers.sum() == 8 and remote.warnings


def test_both_poses_inverted_are_answered_right_and_said(client):
    b = _handeye.broken("inverted_both", seed=1)
    remote = client.calibrate(b.base_flange, b.camera_target)
    _assert_same(remote, handeye.calibrate(b.base_flange, b.camera_target))
    assert any("Solved as inverted" in w for w in remote.warnings)
    deg, mm = _handeye.pose_error(remote.x, b.scene.x)
    assert deg < 0.3 and mm < 3.0


def test_camera_scale_travels_with_its_sigma(client):
    """A board 2 % too large: the scale the camera's translations were solved at (1 / 1.02) and
    its σ reach the client."""
    b = _handeye.broken("board_scale", seed=1)
    remote = client.calibrate(b.base_flange, b.camera_target)
    _assert_same(remote, handeye.calibrate(b.base_flange, b.camera_target))
    lam, sigma = remote.camera_scale
    assert 0.0 < sigma < 0.005 and abs(lam - 1.0 / 1.02) < 4.0 * sigma


def test_given_noise_travels_per_pair(client):
    s = _handeye.scene(10, camera_noise=(0.1, 0.5), robot_noise=(0.05, 0.2), seed=7)
    rng = np.random.default_rng(1)
    cams = np.array([_handeye.covariance((0.1, 0.5)) * rng.uniform(0.5, 2.0)
                     for _ in range(10)])
    robot = _handeye.covariance((0.05, 0.2))
    remote = client.calibrate(s.base_flange, s.camera_target, camera_covariance=cams,
                              robot_covariance=robot)
    local = handeye.calibrate(s.base_flange, s.camera_target, camera_covariance=cams,
                              robot_covariance=robot)
    assert remote.noise_model == "given"
    _assert_same(remote, local)


def test_corners_travel_with_one_camera_matrix(client, stub):
    s = _handeye.scene(10, camera_noise=(0.1, 0.5), seed=11)
    cs = _handeye.corners(s, 0.2, seed=3)
    remote = client.calibrate(s.base_flange, s.camera_target, corners=cs, refine_focal=True)
    local = handeye.calibrate(s.base_flange, s.camera_target, corners=cs, refine_focal=True)
    _assert_same(remote, local)
    np.testing.assert_allclose(remote.reprojection, local.reprojection, rtol=1e-8)
    assert remote.focal_scale == pytest.approx(local.focal_scale, rel=1e-10)
    assert remote.focal_sigma == pytest.approx(local.focal_sigma, rel=1e-8)
    assert remote.pixel_sigma == pytest.approx(local.pixel_sigma, rel=1e-8)
    # corners on some pairs only, a camera matrix missing or wrong, a stray corner coordinate
    ok = calibrate_msg(s.base_flange, s.camera_target, corners=cs)

    def case(edit):
        r = pb.CalibrateRequest()
        r.CopyFrom(ok)
        edit(r)
        return _details(stub, r)

    for edit, expected in [
        (lambda r: r.pairs[4].ClearField("corners"), "pairs[4].corners: required, as pairs[0]"),
        (lambda r: r.ClearField("camera_matrix"), "camera_matrix: 0 values; 9"),
        (lambda r: r.camera_matrix.__setitem__(3, 0.5), "camera_matrix: not a camera matrix"),
        (lambda r: r.pairs[2].corners.image_points.append(1.0),
         "pairs[2].corners.image_points: "),
        (lambda r: r.pairs[2].corners.target_points.extend([0.0, 0.0, 0.0]),
         "pairs[2].corners.image_points: "),
        (lambda r: [p.ClearField("corners") for p in r.pairs], "camera_matrix: only with corners"),
        (lambda r: setattr(r, "pixel_sigma", -1.0), "pixel_sigma: must be a positive number"),
    ]:
        code, details = case(edit)
        assert code == grpc.StatusCode.INVALID_ARGUMENT, details
        assert details.startswith(expected), details


def test_outliers_are_rejected_with_reasons_and_robust_is_the_default(client, stub):
    s = _handeye.scene(15, camera_noise=(0.1, 0.5), seed=2)
    bad = s.camera_target.copy()
    for i in (3, 9, 12):         # 20 %: the board seen 10 cm and 20 deg from where it was
        bad[i] = _handeye.perturb(bad[i], (20.0, 100.0), np.random.default_rng(i))
    remote = client.calibrate(s.base_flange, bad)
    local = handeye.calibrate(s.base_flange, bad)
    _assert_same(remote, local)
    assert {3, 9, 12} <= {r.index for r in remote.rejected}
    assert all(r.reason for r in remote.rejected)
    # the request without `robust` is the robust solve; robust=false keeps every pair
    request = calibrate_msg(s.base_flange, bad)
    request.ClearField("robust")
    unset = stub.Calibrate(request)
    assert [r.index for r in unset.rejected] == [r.index for r in remote.rejected]
    kept = client.calibrate(s.base_flange, bad, robust=False)
    assert not kept.rejected


def _details(stub, request) -> tuple[grpc.StatusCode, str]:
    with pytest.raises(grpc.RpcError) as e:
        stub.Calibrate(request)
    return e.value.code(), e.value.details()


def test_malformed_requests_are_named_by_field(stub, client):
    s = _handeye.scene(6, seed=1)
    ok = calibrate_msg(s.base_flange, s.camera_target)

    def case(edit):
        r = pb.CalibrateRequest()
        r.CopyFrom(ok)
        edit(r)
        return _details(stub, r)

    cases = [
        (lambda r: r.ClearField("setup"), "setup: required: SETUP_EYE_IN_HAND"),
        (lambda r: setattr(r, "setup", 7), "setup: unknown Setup value 7"),
        (lambda r: r.pairs[1].ClearField("camera_to_target"),
         "pairs[1].camera_to_target: required"),
        (lambda r: setattr(r.pairs[3].base_to_flange.orientation, "w", 3.0),
         "pairs[3].base_to_flange.orientation: quaternion norm"),
        (lambda r: setattr(r.pairs[2].camera_to_target.position, "x", float("nan")),
         "pairs[2].camera_to_target.position"),
        (lambda r: r.pairs[4].camera_covariance.extend([1.0] * 36),
         "pairs[0].camera_covariance: 0 values; expected 36"),
        (lambda r: [p.camera_covariance.extend([0.0] * 35) for p in r.pairs],
         "pairs[0].camera_covariance: 35 values; expected 36"),
    ]
    for edit, expected in cases:
        code, details = case(edit)
        assert code == grpc.StatusCode.INVALID_ARGUMENT, details
        assert details.startswith(expected), details
    # a covariance the domain refuses: named at its pair, as the domain names its index
    neg = -np.eye(6)[None].repeat(6, 0)
    with pytest.raises(ValueError) as e:
        handeye.calibrate(s.base_flange, s.camera_target, camera_covariance=neg)
    with pytest.raises(InvalidArgument) as remote:
        client.calibrate(s.base_flange, s.camera_target, camera_covariance=neg)
    assert str(remote.value) == str(calibrate_error(e.value))
    assert str(remote.value).startswith("pairs")
    # over the server's limit
    many = _handeye.scene(41, seed=3)
    code, details = _details(stub, calibrate_msg(many.base_flange, many.camera_target))
    assert code == grpc.StatusCode.INVALID_ARGUMENT
    assert details == "pairs: 41 exceed the server limit of 40 per request"


def _degenerate():
    """Unusable data sets: ``(base_flange, camera_target, setup, a word of the reason)``."""
    from dqpose import dq
    s = _handeye.scene(10, seed=5)
    still = np.repeat(s.base_flange[:1], 10, axis=0)
    out = {"two poses": (s.base_flange[:2], s.camera_target[:2], "eye_in_hand", "at least 3")}
    # pure translation: the flange moves but never turns
    qs, ts = dq.to_pose(s.base_flange)
    F = dq.from_pose(np.repeat(qs[:1], 10, 0), ts)
    out["pure translation"] = (F, handeye.view_at(F, s.x, s.z, "eye_in_hand"),
                               "eye_in_hand", "pure translation")
    # rotations about one axis only
    angles = np.radians(np.linspace(-40, 40, 10))
    R = np.array([_handeye.pose([0.0, 0.0, a], [0.4 + 0.01 * k, 0.1, 0.4])
                  for k, a in enumerate(angles)])
    out["parallel axes"] = (R, handeye.view_at(R, s.x, s.z, "eye_in_hand"),
                            "eye_in_hand", "parallel")
    out["the same pose ten times"] = (still, np.repeat(s.camera_target[:1], 10, 0),
                                      "eye_in_hand", "duplicates")
    # both poses inverted, the board's z out of it: fits as well as the truth, and the target's
    # depth does not tell the readings apart
    out_of_board = dq.mul(s.camera_target, _handeye.rotation([np.pi, 0.0, 0.0]))
    out["both poses inverted, undecidable"] = (dq.inv(s.base_flange), dq.inv(out_of_board),
                                               "eye_in_hand", "cannot tell")
    out["swapped setup"] = (s.base_flange, s.camera_target, "eye_to_hand", "swapped")
    out["camera poses inverted"] = (s.base_flange, dq.inv(s.camera_target), "eye_in_hand",
                                    "inverted")
    q, t = dq.to_pose(s.base_flange)
    out["millimetres as metres"] = (dq.from_pose(q, 1000 * t), s.camera_target, "eye_in_hand",
                                    "millimetres")
    return out


@pytest.mark.parametrize("name", list(_degenerate()))
def test_unusable_data_is_failed_precondition_with_the_solvers_reason(client, name):
    base_flange, camera_target, setup, reason = _degenerate()[name]
    with pytest.raises(Infeasible) as local:
        handeye.calibrate(base_flange, camera_target, setup)
    with pytest.raises(RpcError) as remote:
        client.calibrate(base_flange, camera_target, setup)
    assert remote.value.code == grpc.StatusCode.FAILED_PRECONDITION, remote.value.details
    # the domain's reason with the request's field names: "pairs.base_to_flange, ...: ..."
    assert remote.value.details == str(calibrate_error(local.value))
    assert reason in remote.value.details
    assert "base_flange" not in remote.value.details and "camera_target" not in \
        remote.value.details
    # the server is still there
    s = _handeye.scene(6, seed=1)
    assert client.calibrate(s.base_flange, s.camera_target).x.shape == (8,)
