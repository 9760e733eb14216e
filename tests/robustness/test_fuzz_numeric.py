"""Every numeric field of Fuse, StreamFuse, Plan, Smooth and Calibrate at extremes (NaN, +-inf,
5e-324, 1e308, ...), a few at a time in otherwise valid requests, against a server process: never
INTERNAL, never a NaN or infinity in an answer, every refusal starting with the request's field
path and its numbers readable (no run of 16 digits), and the server healthy at the end.
(Blend and Interpolate have theirs in tests/rpc/test_server.py.)"""
from __future__ import annotations

import math
import re

import grpc
import numpy as np
import pytest
from google.protobuf.descriptor import FieldDescriptor
from hypothesis import given, settings
from hypothesis import strategies as st

from service import dq, lie, trajectory
from service.rpc import convert
from service.rpc._proto.dqpose.v1 import fusion_pb2 as fpb
from service.rpc._proto.dqpose.v1 import fusion_pb2_grpc as fpb_grpc
from service.rpc._proto.dqpose.v1 import handeye_pb2_grpc as hpb_grpc
from service.rpc._proto.dqpose.v1 import trajectories_pb2 as tpb
from service.rpc._proto.dqpose.v1 import trajectories_pb2_grpc as tpb_grpc

from _served import served
from test_handeye_limits import H

EXTREME = st.sampled_from([0.0, -0.0, 1.0, -1.0, 0.5, 1e308, -1e308, 1.7976931348623157e308,
                           5e-324, -5e-324, 2.2250738585072014e-308, 1e-300, 1e300, -1e300,
                           1e30, 1e-30, 1e17, 1e15, math.nan, math.inf, -math.inf])
REFUSED = {grpc.StatusCode.INVALID_ARGUMENT, grpc.StatusCode.FAILED_PRECONDITION,
           grpc.StatusCode.RESOURCE_EXHAUSTED}
LONG_NUMBER = re.compile(r"\d{16,}")


@pytest.fixture(scope="module")
def server():
    with served() as s:
        yield s
        assert s.health() == "SERVING"


def doubles(msg, path=""):
    """``(path, value)`` of every double and float field set in ``msg``, nested ones too."""
    for f, v in msg.ListFields():
        where = f"{path}{f.name}"
        values = v if f.is_repeated else [v]
        for k, x in enumerate(values):
            at = f"{where}[{k}]" if f.is_repeated else where
            if f.type in (FieldDescriptor.TYPE_DOUBLE, FieldDescriptor.TYPE_FLOAT):
                yield at, x
            elif f.type == FieldDescriptor.TYPE_MESSAGE:
                yield from doubles(x, at + ".")


def numeric_paths(msg):
    """Setters of every double field of ``msg`` (repeated ones element by element), by path."""
    out = []

    def walk(m, path):
        for f in m.DESCRIPTOR.fields:
            if f.type in (FieldDescriptor.TYPE_DOUBLE, FieldDescriptor.TYPE_FLOAT):
                if f.is_repeated:
                    for k in range(len(getattr(m, f.name))):
                        out.append((f"{path}{f.name}[{k}]",
                                    lambda v, m=m, f=f, k=k: getattr(m, f.name).__setitem__(k, v)))
                else:
                    out.append((f"{path}{f.name}", lambda v, m=m, f=f: setattr(m, f.name, v)))
            elif f.type == FieldDescriptor.TYPE_MESSAGE:
                if f.is_repeated:
                    for k, sub in enumerate(getattr(m, f.name)):
                        walk(sub, f"{path}{f.name}[{k}].")
                elif m.HasField(f.name):
                    walk(getattr(m, f.name), f"{path}{f.name}.")
    walk(msg, "")
    return out


def mutated(base, draw_values):
    """A copy of ``base`` with some of its numeric fields set to extremes."""
    msg = type(base)()
    msg.CopyFrom(base)
    paths = numeric_paths(msg)
    picks, values = draw_values(len(paths))
    for i, v in zip(picks, values):
        paths[i % len(paths)][1](v)
    return msg


def choices():
    return st.tuples(st.lists(st.integers(0, 10_000), min_size=1, max_size=3),
                     st.lists(EXTREME, min_size=3, max_size=3))


def check_refusal(code, details, fields):
    assert code in REFUSED, (code, details)
    assert re.match(r"^(%s)\b" % "|".join(fields), details), details
    assert not LONG_NUMBER.search(details), details


def check_answer(msg):
    for path, x in doubles(msg):
        assert math.isfinite(x), (path, x)


def call(fn, fields):
    try:
        answer = fn()
    except grpc.RpcError as e:
        check_refusal(e.code(), e.details(), fields)
        return None
    for a in (answer if isinstance(answer, list) else [answer]):
        check_answer(a)
    return answer


# ---- the base requests: valid, with every option that has a number set

def _scene(n=6, seed=0):
    rng = np.random.default_rng(seed)
    X = lie.se3_exp(rng.normal(size=6))
    return dq.mul(X, lie.se3_exp(0.01 * rng.normal(size=(n, 6)))), np.broadcast_to(
        np.diag([1e-4] * 3 + [1e-6] * 3), (n, 6, 6))


def _fuse_base():
    Z, S = _scene()
    return fpb.FuseRequest(
        measurements=convert.measurement_msgs(Z, S, names=["a", "b"] * 3,
                                              times=np.linspace(0, 0.05, 6)),
        options=convert.options_msg(robust=True, sources=[
            __import__("service.fusion").fusion.Source("a", latency=0.01, latency_sigma=0.005),
            __import__("service.fusion").fusion.Source("b")], probability=0.99, max_skew=1.0,
            max_extrapolation=0.5, twist_covariance=np.eye(6),
            acceleration_psd=np.eye(6) * 1e-3))


FUSE = _fuse_base()
LIMITS = trajectory.Limits(0.2, 1.0, 1.0, 2.0, 10.0, 20.0)
_T = np.linspace(0.0, 2.0, 40)
_PATH = lie.se3_exp(np.column_stack([np.outer(0.1 * np.sin(_T), np.ones(3)),
                                     np.outer(0.1 * np.cos(_T), np.ones(3))]))
PLAN = convert.plan_msg([trajectory.Waypoint(_PATH[0]), trajectory.Waypoint(_PATH[20], 0.0, 0.01),
                         trajectory.Waypoint(_PATH[39])], LIMITS, 100.0,
                        start_velocity=np.zeros(6))
SMOOTH = tpb.SmoothRequest(poses=convert.stamped_msgs(_T, _PATH),
                           limits=convert.limits_msg(LIMITS), smoothing=1.0, rate_hz=50.0)
_S = H.scene(6, seed=3)
CALIBRATE = convert.calibrate_msg(_S.base_flange, _S.camera_target, _S.setup,
                                  camera_covariance=_S.camera_covariance,
                                  corners=H.corners(_S), pixel_sigma=0.2)
for _p in CALIBRATE.pairs:          # fewer corners a view: the request stays quick
    del _p.corners.target_points[12:], _p.corners.image_points[8:]


@settings(max_examples=120)
@given(choices())
def test_fuse(server, picks):
    request = mutated(FUSE, lambda n: picks)
    call(lambda: fpb_grpc.FusionStub(server.channel).Fuse(request, timeout=60),
         ("measurements", "options"))


@settings(max_examples=60)
@given(choices(), EXTREME, EXTREME)
def test_stream_fuse(server, picks, rate, window):
    first = fpb.FuseStreamRequest(output_rate=rate)
    first.options.CopyFrom(FUSE.options)
    first.options.window = window
    first.options.time = 0.0
    rest = mutated(fpb.FuseStreamRequest(measurements=FUSE.measurements), lambda n: picks)
    for m in rest.measurements:
        m.body = "b"
    try:
        answers = list(fpb_grpc.FusionStub(server.channel).StreamFuse(
            iter([first, rest, fpb.FuseStreamRequest(measurements=FUSE.measurements)]), timeout=60))
    except grpc.RpcError as e:      # the first request's options refused: the stream ends
        check_refusal(e.code(), e.details(), ("requests",))
        return
    for a in answers:
        if a.HasField("error"):
            assert re.match(r"^requests\[\d+\]", a.error.details), a.error.details
            assert not LONG_NUMBER.search(a.error.details), a.error.details
        else:
            check_answer(a)


@settings(max_examples=120)
@given(choices())
def test_plan(server, picks):
    request = mutated(PLAN, lambda n: picks)
    call(lambda: list(tpb_grpc.TrajectoriesStub(server.channel).Plan(request, timeout=60)),
         ("waypoints", "limits", "rate_hz", "interpolation", "start_linear_velocity",
          "start_angular_velocity"))


@settings(max_examples=80)
@given(choices())
def test_smooth(server, picks):
    request = mutated(SMOOTH, lambda n: picks)
    call(lambda: tpb_grpc.TrajectoriesStub(server.channel).Smooth(request, timeout=120),
         ("poses", "limits", "smoothing", "rate_hz"))


@settings(max_examples=80)
@given(choices())
def test_calibrate(server, picks):
    request = mutated(CALIBRATE, lambda n: picks)
    call(lambda: hpb_grpc.HandEyeStub(server.channel).Calibrate(request, timeout=120),
         ("setup", "pairs", "robust", "camera_matrix", "refine_focal", "pixel_sigma"))
