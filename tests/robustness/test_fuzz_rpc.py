"""Every numeric field of every request the server takes, fuzzed on a real server on 127.0.0.1.

Each RPC starts from one legal request; hypothesis sets one to three of its numeric fields (any
depth, any repeated element, set or not) to extremes (NaN, ±Inf, ±0, 5e-324, 1e±300, the type's
bounds) or arbitrary values, and sends it. Whatever the input, the answer is OK or a named
refusal (INVALID_ARGUMENT, FAILED_PRECONDITION, RESOURCE_EXHAUSTED, OUT_OF_RANGE) whose message
starts with the request's field path and writes its numbers readably (no run of 16 digits),
never INTERNAL/UNKNOWN, never a stuck call; no answer carries NaN, and a stream's error entries
name their message (``requests[k]``) too; and the server still answers health right after.
"""
from __future__ import annotations

import json
import math
import os
import re
import subprocess
import sys
import threading

import grpc
import numpy as np
import pytest
from google.protobuf import descriptor as _descriptor
from google.protobuf import json_format
from grpc_health.v1 import health_pb2, health_pb2_grpc
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dqpose.rpc._proto.dqpose.v1 import blending_pb2 as bpb
from dqpose.rpc._proto.dqpose.v1 import fusion_pb2 as fpb
from dqpose.rpc._proto.dqpose.v1 import handeye_pb2 as hpb
from dqpose.rpc._proto.dqpose.v1 import trajectories_pb2 as tpb
from dqpose.rpc.handeye_convert import calibrate_msg

_TESTS = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
from tests import _handeye  # noqa: E402

ROOT = os.path.dirname(_TESTS)

#: a call that takes longer than this is a server that stopped answering (the heaviest legal
#: request of these sizes takes ~2 s on a quiet machine: a StreamFuse with the acceleration model
#: and a latency estimate; one took over 20 s in a suite run at a load of 5-7, and passed again)
CALL_DEADLINE = 60.0
#: health is answered within this while anything else runs (generous for a loaded machine)
HEALTH_DEADLINE = 2.0
#: answers read from a server stream before the call is closed
MAX_STREAM_ANSWERS = 200

REFUSALS = {grpc.StatusCode.INVALID_ARGUMENT, grpc.StatusCode.FAILED_PRECONDITION,
            grpc.StatusCode.RESOURCE_EXHAUSTED, grpc.StatusCode.OUT_OF_RANGE}

#: a number written with all its digits (a repr or a 300-digit count), not one a person reads
LONG_NUMBER = re.compile(r"\d{16,}")

_F = _descriptor.FieldDescriptor
FLOATS = {_F.TYPE_DOUBLE, _F.TYPE_FLOAT}
INTS = {_F.TYPE_INT32: (-2**31, 2**31 - 1), _F.TYPE_SINT32: (-2**31, 2**31 - 1),
        _F.TYPE_INT64: (-2**63, 2**63 - 1), _F.TYPE_SINT64: (-2**63, 2**63 - 1),
        _F.TYPE_UINT32: (0, 2**32 - 1), _F.TYPE_UINT64: (0, 2**64 - 1),
        _F.TYPE_FIXED32: (0, 2**32 - 1), _F.TYPE_FIXED64: (0, 2**64 - 1)}


def _pose(x=0.0, y=0.0, z=0.0, angle=0.0):
    return {"position": {"x": x, "y": y, "z": z},
            "orientation": {"w": math.cos(angle / 2), "z": math.sin(angle / 2)}}


def _cov(sigma_rot=0.01, sigma_t=0.002):
    return list(np.diag([sigma_rot ** 2] * 3 + [sigma_t ** 2] * 3).ravel())


def _limits():
    return {"max_linear_velocity": 0.25, "max_angular_velocity": 1.0,
            "max_linear_acceleration": 1.0, "max_angular_acceleration": 2.0,
            "max_linear_jerk": 10.0, "max_angular_jerk": 20.0}


def _measurements(n=4, t0=0.0, body="tool"):
    return [{"source": "cam" if i % 2 else "arm", "body": body, "time": t0 + 0.01 * i,
             "pose": _pose(0.3 + 0.001 * i, 0.1, 0.2, 0.1 + 0.002 * i), "covariance": _cov()}
            for i in range(n)]


def _fusion_options(light=False):
    """Every option set; ``light``: without the latency estimate and the acceleration model,
    which make a fit ~100x dearer (their fields are fuzzed all the same, from unset)."""
    cam = {"name": "cam", "extrinsic": _pose(0.01, 0, 0, 0.01), "body_offset": _pose(0, 0, 0.001),
           "latency": 0.02}
    options = {"robust": True, "max_skew": 0.5, "probability": 0.99, "max_extrapolation": 0.2,
               "window": 0.2, "twist_covariance": _cov(0.5, 0.5),
               "sources": [{"name": "arm", "latency": 0.001}, cam]}
    if not light:
        options["acceleration_psd"] = _cov(0.1, 0.1)
        cam["latency_sigma"] = 0.005
    return options


def _calibrate():
    s = _handeye.scene(8, "eye_in_hand", camera_noise=(0.1, 0.5), seed=3)
    cam = np.diag([1e-6] * 3 + [1e-8] * 3)
    return calibrate_msg(s.base_flange, s.camera_target, "eye_in_hand",
                         camera_covariance=np.broadcast_to(cam, (8, 6, 6)))


def _msg(cls, d):
    return json_format.ParseDict(d, cls())


def _requests(light=False):
    """(service, method, kind, request class, response class, legal request(s))"""
    poses = [_pose(0.1, 0, 0, 0.0), _pose(0.3, 0.1, 0, 0.5), _pose(0.2, 0.2, 0.1, -0.3)]
    blend = {"poses": poses, "weights": [1, 2, 3], "method": "METHOD_DIB", "tolerance": 1e-10,
             "max_iterations": 50}
    keyframes = [{"time": 0.1 * i, "pose": p} for i, p in enumerate(poses)]
    waypoints = [{"pose": _pose(0.3, 0.0, 0.2), "time": 0.0},
                 {"pose": _pose(0.35, 0.0, 0.2, 0.2), "blend_radius": 0.01},
                 {"pose": _pose(0.35, 0.05, 0.2, 0.3), "time": 3.0}]
    plan = {"waypoints": waypoints, "limits": _limits(), "rate_hz": 50,
            "start_linear_velocity": {"x": 0.001}, "start_angular_velocity": {"z": 0.001}}
    smooth = {"poses": [{"time": 0.05 * i, "pose": _pose(0.3 + 0.002 * i, 0, 0.2, 0.002 * i)}
                        for i in range(20)],
              "limits": _limits(), "smoothing": 1.0, "rate_hz": 100}
    return [
        ("Blending", "Blend", "unary", bpb.BlendRequest, bpb.BlendResponse,
         _msg(bpb.BlendRequest, blend)),
        ("Blending", "BlendBatch", "unary", bpb.BlendBatchRequest, bpb.BlendBatchResponse,
         _msg(bpb.BlendBatchRequest, {"requests": [blend, blend]})),
        ("Blending", "Interpolate", "unary", bpb.InterpolateRequest, bpb.InterpolateResponse,
         _msg(bpb.InterpolateRequest, {"keyframes": keyframes, "times": [0.0, 0.05, 0.2],
                                       "interpolation": "INTERPOLATION_SCREW"})),
        ("Blending", "BlendStream", "stream", bpb.BlendRequest, bpb.BlendResponse,
         [_msg(bpb.BlendRequest, blend), _msg(bpb.BlendRequest, blend)]),
        ("Fusion", "Fuse", "unary", fpb.FuseRequest, fpb.FusedPose,
         _msg(fpb.FuseRequest, {"measurements": _measurements(),
                                "options": {**_fusion_options(light), "window": 0}})),
        ("Fusion", "StreamFuse", "stream", fpb.FuseStreamRequest, fpb.FusedPose,
         [_msg(fpb.FuseStreamRequest, {"options": _fusion_options(light), "output_rate": 50,
                                       "measurements": _measurements()}),
          _msg(fpb.FuseStreamRequest, {"measurements": _measurements(t0=0.05)}),
          _msg(fpb.FuseStreamRequest, {"measurements": _measurements(t0=0.1, body="b")})]),
        ("Trajectories", "Plan", "server_stream", tpb.PlanRequest, tpb.TrajectorySample,
         _msg(tpb.PlanRequest, plan)),
        ("Trajectories", "Smooth", "unary", tpb.SmoothRequest, tpb.SmoothResponse,
         _msg(tpb.SmoothRequest, smooth)),
        ("HandEye", "Calibrate", "unary", hpb.CalibrateRequest, hpb.CalibrateResponse,
         _calibrate()),
    ]


REQUESTS = _requests()
LIGHT = _requests(light=True)


def numeric_paths(msg, prefix=()):
    """Every numeric field reachable in ``msg``: ``(path, field)`` with path a tuple of
    (field name, index or None); unset scalars included, unset sub-messages entered one level
    (a field the request left out is input too)."""
    out = []
    for f in msg.DESCRIPTOR.fields:
        if f.type in FLOATS or f.type in INTS:
            if f.is_repeated:
                n = len(getattr(msg, f.name))
                for i in sorted({0, 1, n - 1, n} - {-1}):
                    if i <= n:
                        out.append((prefix + ((f.name, i),), f))
            else:
                out.append((prefix + ((f.name, None),), f))
        elif f.type == _F.TYPE_MESSAGE:
            if f.is_repeated:
                items = getattr(msg, f.name)
                for i in sorted({0, 1, len(items) - 1} - {-1}):
                    if i < len(items):
                        out += numeric_paths(items[i], prefix + ((f.name, i),))
            elif msg.HasField(f.name):
                out += numeric_paths(getattr(msg, f.name), prefix + ((f.name, None),))
            elif len(prefix) < 3:
                out += numeric_paths(f.message_type._concrete_class(), prefix + ((f.name, None),))
    return out


def set_path(msg, path, value):
    *parents, (name, index) = path
    for pname, pindex in parents:
        msg = getattr(msg, pname)[pindex] if pindex is not None else getattr(msg, pname)
    if index is None:
        setattr(msg, name, value)
    else:
        items = getattr(msg, name)
        if index < len(items):
            items[index] = value
        else:
            items.append(value)


def path_text(path):
    return ".".join(f"{n}[{i}]" if i is not None else n for n, i in path)


EXTREME_FLOATS = [math.nan, math.inf, -math.inf, 0.0, -0.0, 5e-324, -5e-324, 1e-300, 1e300,
                  -1e300, 1.7976931348623157e308, 1e17, 1e9, 1e8, -1.0, 1e-9, 0.5, 3.0]


def value_for(field):
    if field.type in FLOATS:
        v = st.sampled_from(EXTREME_FLOATS) | st.floats(allow_nan=True, allow_infinity=True)
        if field.type == _F.TYPE_FLOAT:
            v = v.map(lambda x: float(np.float32(x)) if abs(x) < 3e38 or not math.isfinite(x)
                      else math.copysign(math.inf, x))
        return v
    lo, hi = INTS[field.type]
    return st.sampled_from([lo, hi, 0, 1, 2, 1000, 10**6]) | st.integers(lo, hi)


class ServedProcess:
    """``dqpose serve --port 0`` in a process of its own, so that a server that stops answering
    is seen from outside rather than taking the test's own interpreter with it; its log is kept
    (``log``) for the failure messages."""

    def __init__(self):
        self.proc = subprocess.Popen([sys.executable, "-m", "dqpose.cli", "serve", "--port", "0"],
                                     cwd=ROOT, stderr=subprocess.PIPE, text=True)
        self.log: list[str] = []
        for line in self.proc.stderr:
            self.log.append(line)
            if line.startswith("{") and json.loads(line).get("event") == "serving":
                self.target = json.loads(line)["address"]
                break
        else:
            raise RuntimeError("the server ended before serving:\n" + "".join(self.log))
        threading.Thread(target=self._drain, daemon=True).start()

    def _drain(self):
        for line in self.proc.stderr:
            self.log.append(line)
            del self.log[:-200]

    def close(self):
        self.proc.kill()
        self.proc.wait()


@pytest.fixture
def channel():
    """A server of its own for each RPC: one that an RPC broke does not fail the next's tests
    (under hypothesis it serves every example of the test)."""
    served = ServedProcess()
    try:
        with grpc.insecure_channel(served.target) as ch:
            yield ch
    finally:
        served.close()


def _nan_fields(msg, prefix=""):
    bad = []
    for f, v in msg.ListFields():
        name = f"{prefix}{f.name}"
        values = v if f.is_repeated else [v]
        for i, x in enumerate(values):
            if f.type == _F.TYPE_MESSAGE:
                bad += _nan_fields(x, f"{name}[{i}]." if f.is_repeated else name + ".")
            elif f.type in FLOATS and math.isnan(x):
                bad.append(name)
    return bad


def call(channel, service, method, kind, req_cls, resp_cls, request):
    path = f"/dqpose.v1.{service}/{method}"
    ser, de = req_cls.SerializeToString, resp_cls.FromString
    if kind == "unary":
        return [channel.unary_unary(path, ser, de)(request, timeout=CALL_DEADLINE)]
    if kind == "server_stream":
        it = channel.unary_stream(path, ser, de)(request, timeout=CALL_DEADLINE)
    else:
        it = channel.stream_stream(path, ser, de)(iter(request), timeout=CALL_DEADLINE)
    out = []
    try:
        for m in it:
            out.append(m)
            if len(out) >= MAX_STREAM_ANSWERS:
                break
    finally:
        it.cancel()
    return out


def _fields(req_cls):
    """What a refusal may start with: a field of the request (a stream's messages are
    ``requests[k]``)."""
    return tuple(f.name for f in req_cls.DESCRIPTOR.fields) + ("requests",)


def _check_text(details, fields, what):
    assert re.match(r"^(%s)\b" % "|".join(fields), details), \
        f"{what}: {details!r} names no field of the request"
    assert not LONG_NUMBER.search(details), f"{what}: {details!r} has an unreadable number"


def _check_answer(channel, rpc, request, edits):
    """AssertionError naming the call and the edits if the answer breaks a rule above."""
    service, method, kind, req_cls, resp_cls, _ = rpc
    what = f"{service}/{method} with " + ", ".join(f"{path_text(p)}={v!r}" for p, v in edits)
    try:
        answers = call(channel, service, method, kind, req_cls, resp_cls, request)
    except grpc.RpcError as e:
        if e.code() == grpc.StatusCode.CANCELLED:      # our own cancel after enough answers
            answers = []
        else:
            assert e.code() in REFUSALS, f"{what}: {e.code().name} {e.details()!r}"
            _check_text(e.details(), _fields(req_cls), what)
            answers = []
    for a in answers:
        bad = _nan_fields(a)
        assert not bad, f"{what}: NaN in the answer's {bad}"
        if "error" in a.DESCRIPTOR.fields_by_name and a.HasField("error"):
            _check_text(a.error.details, ("requests",), what)
    health = health_pb2_grpc.HealthStub(channel)
    status = health.Check(health_pb2.HealthCheckRequest(), timeout=HEALTH_DEADLINE).status
    assert status == health_pb2.HealthCheckResponse.SERVING, f"after {what}: health {status}"


def _edited(base, k, edits):
    """A copy of the request (or of the stream's requests) with ``edits`` made in message k."""
    if isinstance(base, list):
        request = [type(m)() for m in base]
        for r, m in zip(request, base):
            r.CopyFrom(m)
        mutated = request[k]
    else:
        request = type(base)()
        request.CopyFrom(base)
        mutated = request
    for path, value in edits:
        set_path(mutated, path, value)
    return request


def _messages(base):
    return base if isinstance(base, list) else [base]


@pytest.mark.heavy
@pytest.mark.parametrize("rpc", LIGHT, ids=[f"{r[0]}.{r[1]}" for r in LIGHT])
def test_every_field_at_every_extreme(channel, rpc):
    """Each numeric field alone at each extreme value: every case, not a sample of them."""
    failures = []
    for k, msg in enumerate(_messages(rpc[5])):
        for path, field in numeric_paths(msg):
            values = EXTREME_FLOATS if field.type in FLOATS else \
                sorted({*INTS[field.type], 0, 1, 2, 10**6})
            for v in values:
                if field.type == _F.TYPE_FLOAT and math.isfinite(v) and abs(v) > 3e38:
                    continue
                try:
                    _check_answer(channel, rpc, _edited(rpc[5], k, [(path, v)]), [(path, v)])
                except AssertionError as e:
                    failures.append(str(e).splitlines()[0])
                    if "health" in failures[-1] or "DEADLINE_EXCEEDED" in failures[-1]:
                        # the server stopped answering: nothing more to learn from it
                        pytest.fail("\n".join(failures))
                except grpc.RpcError as e:             # health itself did not answer
                    failures.append(f"{path_text(path)}={v!r}: health {e.code().name}")
                    pytest.fail("\n".join(failures))
    assert not failures, f"{len(failures)} cases:\n" + "\n".join(failures)


@pytest.mark.parametrize("rpc", REQUESTS, ids=[f"{r[0]}.{r[1]}" for r in REQUESTS])
@settings(max_examples=int(os.environ.get("FUZZ_EXAMPLES", "120")),
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(data=st.data())
def test_no_numeric_input_breaks_an_rpc(channel, rpc, data):
    base = rpc[5]
    first = base[0] if isinstance(base, list) else base
    # in a stream, the fields of every message are fuzzed (the first carries the options)
    k = data.draw(st.integers(0, len(base) - 1), label="message") if isinstance(base, list) else 0
    target = base[k] if isinstance(base, list) else first
    paths = numeric_paths(target)
    chosen = data.draw(st.lists(st.sampled_from(range(len(paths))), min_size=1, max_size=3,
                                unique=True), label="fields")
    edits = [(paths[i][0], data.draw(value_for(paths[i][1]), label=path_text(paths[i][0])))
             for i in chosen]
    _check_answer(channel, rpc, _edited(base, k, edits), edits)


@pytest.mark.parametrize("rpc", REQUESTS, ids=[f"{r[0]}.{r[1]}" for r in REQUESTS])
def test_the_legal_requests_are_answered(channel, rpc):
    """The fuzz starts from requests the server answers: a refusal here would make every fuzzed
    case a refusal for the same reason."""
    service, method, kind, req_cls, resp_cls, request = rpc
    answers = call(channel, service, method, kind, req_cls, resp_cls, request)
    assert answers, f"{service}/{method}: no answer"
