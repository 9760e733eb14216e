"""dqpose.rpc.client (NumPy in/out) and the `dqpose blend | interpolate | health` commands, against
a real server on 127.0.0.1."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import grpc
import numpy as np
import pytest

from dqpose import dq
from dqpose.interpolate import interpolate
from dqpose.rpc.client import Client, InvalidArgument, RequestTooLarge, RpcError
from tests.rpc._grpc_server import ServerThread

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


@pytest.fixture(scope="module")
def server():
    with ServerThread(token="tok") as s:
        yield s


@pytest.fixture(scope="module")
def client(server):
    with Client(server.target, token="tok") as c:
        yield c


def _poses(seed, n):
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return dq.from_pose(q, rng.uniform(-1, 1, (n, 3)))


def _same(a, b, atol=1e-9):
    a, b = np.asarray(a), np.asarray(b)
    s = np.sign(np.sum(a[..., :4] * b[..., :4], axis=-1, keepdims=True))
    np.testing.assert_allclose(a * s, b, atol=atol)


def test_blend_round_trips_numpy(client):
    dqs = _poses(1, 7)
    w = np.arange(1.0, 8.0)
    for method in ("dib", "dlb", "dec", "log", "lin"):
        got = client.blend(dqs, w, method)
        assert got.shape == (8,)
        _same(got, dq.blend(dqs, w, method))
    mean, iterations, residual = client.blend(dqs, return_info=True)
    info = dq.dib(dqs, return_info=True)
    _same(mean, info.mean)
    assert iterations == int(info.iterations) and residual < 1e-9


def test_interpolate_round_trips_numpy(client):
    dqs_k = _poses(2, 3)
    times = np.linspace(0, 2, 41)
    for mode in ("screw", "tool_linear"):
        got = client.interpolate([0, 1, 2], dqs_k, times, mode)
        assert got.shape == (41, 8)
        _same(got, interpolate([0, 1, 2], dqs_k, times, mode))


def test_blend_stream_yields_one_mean_per_batch(client):
    batches = [(_poses(s, 4), None) for s in range(20)]
    got = list(client.blend_stream(batches, method="dlb"))
    assert len(got) == 20
    for (d, _), g in zip(batches, got):
        _same(g, dq.dlb(d))


def test_blend_batch_returns_one_mean_per_set(client):
    sets = np.stack([_poses(s, 5) for s in range(30)])
    weights = np.random.default_rng(1).uniform(0.1, 1.0, (30, 5))
    got = client.blend_batch(sets, weights)
    assert got.shape == (30, 8)
    # the same numbers as the core's batched DIB over a leading axis
    for g, w in zip(got, dq.dib(sets, weights)):
        _same(g, w)
    with pytest.raises(ValueError, match=r"^weights: 2 weight sets for 30 pose sets$"):
        client.blend_batch(sets, weights[:2])


def test_invalid_argument_becomes_value_error_with_the_servers_message(client):
    dqs = _poses(3, 3)
    with pytest.raises(ValueError, match=r"^weights\[2\]: negative weight -1$"):
        client.blend(dqs, [1, 1, -1])
    with pytest.raises(ValueError, match=r"^times\[0\]: 5\.0 is outside the keyframe range"):
        client.interpolate([0, 1], dqs[:2], [5.0])
    with pytest.raises(ValueError, match=r"^method: unknown blending method 'avg'"):
        client.blend(dqs, method="avg")


def test_every_failed_call_is_our_rpc_error_naming_status_and_message(server):
    dqs = _poses(4, 2)
    with Client(server.target, token="nope") as c:
        calls = {"blend": lambda: c.blend(dqs),
                 "blend_batch": lambda: c.blend_batch([dqs, dqs]),
                 "blend_stream": lambda: list(c.blend_stream([(dqs, None)])),
                 "interpolate": lambda: c.interpolate([0, 1], dqs, [0.5])}
        for name, call in calls.items():
            with pytest.raises(RpcError) as e:
                call()
            assert not isinstance(e.value, grpc.RpcError), name
            assert e.value.code == grpc.StatusCode.UNAUTHENTICATED, name
            assert e.value.details == "authorization: invalid bearer token", name
            assert str(e.value) == "UNAUTHENTICATED: authorization: invalid bearer token", name
        assert c.health() == "SERVING"
    with Client("127.0.0.1:1", timeout=2) as c:
        with pytest.raises(RpcError) as e:
            c.blend(dqs)
        assert e.value.code == grpc.StatusCode.UNAVAILABLE
        assert str(e.value).startswith("UNAVAILABLE: ")
        with pytest.raises(RpcError):
            c.health()


def test_invalid_argument_is_both_our_rpc_error_and_a_value_error(client):
    with pytest.raises(InvalidArgument) as e:
        client.blend(_poses(3, 3), [1, 1, -1])
    assert isinstance(e.value, ValueError) and isinstance(e.value, RpcError)
    assert e.value.code == grpc.StatusCode.INVALID_ARGUMENT
    bad = [(_poses(1, 3), None), (np.zeros((2, 8)), None), (_poses(2, 3), None)]
    with pytest.raises(InvalidArgument,
                       match=r"^requests\[1\]\.poses\[0\]\.orientation: zero quaternion"):
        list(client.blend_stream(bad))


def test_blend_batch_of_20000_sets_is_split_under_the_message_limit(client):
    # 20,000 sets of 10 poses are ~14 MB, over the server's 4 MiB and 10,000-request limits
    sets = _poses(6, 20_000 * 10).reshape(20_000, 10, 8)
    got = client.blend_batch(sets, method="dlb")
    assert got.shape == (20_000, 8)
    _same(got, dq.dlb(sets))


def test_blend_batch_takes_lists_of_sets_of_any_size_with_or_without_weights(client):
    rng = np.random.default_rng(7)
    sets = [_poses(s, n) for s, n in enumerate([1, 5, 3, 5, 8, 2])]
    weights = [None, rng.uniform(0.5, 1, 5), None, rng.uniform(0.5, 1, 5), rng.uniform(0.5, 1, 8),
               [1.0, 3.0]]
    got = client.blend_batch(sets, weights)
    for g, d, w in zip(got, sets, weights):
        _same(g, dq.dib(d, w))


def test_blend_batch_splits_under_the_servers_own_limits_and_names_the_set():
    sets = _poses(8, 300 * 4).reshape(300, 4, 8)
    with ServerThread(max_message_bytes=16 * 1024, max_poses=50) as small:
        with Client(small.target, max_message_bytes=16 * 1024, max_poses=50) as c:
            _same(c.blend_batch(sets, method="dlb"), dq.dlb(sets))
            bad = sets.copy()
            bad[237, 2] = 0.0            # in a later call: the message counts from the first set
            with pytest.raises(InvalidArgument,
                               match=r"^requests\[237\]\.poses\[2\]\.orientation: zero quaternion"):
                c.blend_batch(bad)
        with Client(small.target) as c:  # a client that does not know the server's limits
            with pytest.raises(RpcError) as e:
                c.blend_batch(sets)
            assert e.value.code in (grpc.StatusCode.RESOURCE_EXHAUSTED,
                                    grpc.StatusCode.INVALID_ARGUMENT)
            assert e.value.details


def test_interpolate_of_more_times_than_the_server_takes_is_split(client):
    dqs_k = _poses(9, 3)
    times = np.linspace(0, 2, 25_001)
    got = client.interpolate([0, 1, 2], dqs_k, times, "tool_linear")
    assert got.shape == (25_001, 8)
    _same(got, interpolate([0, 1, 2], dqs_k, times, "tool_linear"))
    times[17_500] = 3.0                  # in the second call: named by its place in the whole
    with pytest.raises(InvalidArgument,
                       match=r"^times\[17500\]: 3\.0 is outside the keyframe range"):
        client.interpolate([0, 1, 2], dqs_k, times)


def test_what_cannot_be_split_is_refused_before_sending(client):
    with pytest.raises(RequestTooLarge,
                       match=r"^dqs_k: 10001 keyframes exceed the server limit of 10000"):
        client.interpolate(np.arange(10_001.0), _poses(10, 10_001), [0.5])
    with pytest.raises(RequestTooLarge,
                       match=r"^dqs: 10001 poses exceed the server limit of 10000"):
        client.blend(_poses(10, 10_001))


def test_a_stream_item_of_the_wrong_shape_raises_after_the_answers_before_it(client):
    batches = [(_poses(11, 3), None), (_poses(12, 2), None), (np.zeros((2, 7)), None)]
    got = []
    with pytest.raises(ValueError,
                       match=r"^batches\[2\] dqs: expected shape \(n, 8\), got \(2, 7\)$"):
        for mean in client.blend_stream(batches):
            got.append(mean)
    assert len(got) == 2
    _same(got[1], dq.dib(batches[1][0]))


# --------------------------------------------------------------------------- the CLI

def dqpose(*args, stdin=None):
    return subprocess.run([sys.executable, "-m", "dqpose.cli", *args], input=stdin,
                          capture_output=True, text=True, timeout=60, cwd=ROOT)


@pytest.fixture(scope="module")
def token_file(tmp_path_factory):
    p = tmp_path_factory.mktemp("tok") / "token"
    p.write_text("tok\n")
    return str(p)


@pytest.fixture
def pose_files(tmp_path):
    dqs = _poses(5, 3)
    q, t = dq.to_pose(dqs)
    csv_path = tmp_path / "poses.csv"
    csv_path.write_text("x,y,z,qw,qx,qy,qz,weight\n" + "".join(
        ",".join(map(repr, [*ti.tolist(), *qi.tolist(), w])) + "\n"
        for qi, ti, w in zip(q, t, [1.0, 2.0, 3.0])))
    json_path = tmp_path / "poses.json"
    json_path.write_text(json.dumps({
        "poses": [{"position": dict(zip("xyz", ti)), "orientation": dict(zip("wxyz", qi))}
                  for qi, ti in zip(q.tolist(), t.tolist())],
        "weights": [1, 2, 3], "method": "METHOD_DLB"}))
    return dqs, str(csv_path), str(json_path)


def _csv_pose(text):
    header, row = text.strip().splitlines()
    assert header == "x,y,z,qw,qx,qy,qz"
    v = np.array(row.split(","), dtype=float)
    return dq.from_pose(v[3:], v[:3])


def test_cli_blend_csv_on_the_server_matches_local(server, token_file, pose_files):
    dqs, csv_path, _ = pose_files
    remote = dqpose("blend", csv_path, "--server", server.target, "--token-file", token_file)
    local = dqpose("blend", csv_path, "--local")
    assert remote.returncode == 0 and local.returncode == 0, remote.stderr + local.stderr
    want = dq.dib(dqs, [1.0, 2.0, 3.0])
    _same(_csv_pose(remote.stdout), want, atol=1e-10)
    _same(_csv_pose(local.stdout), want, atol=1e-10)


def test_cli_blend_json_uses_the_files_method_and_prints_json(pose_files):
    dqs, _, json_path = pose_files
    res = dqpose("blend", json_path, "--local")
    assert res.returncode == 0, res.stderr
    out = json.loads(res.stdout)
    p = out["pose"]
    got = dq.from_pose([p["orientation"][k] for k in "wxyz"], [p["position"][k] for k in "xyz"])
    _same(got, dq.dlb(dqs, [1, 2, 3]), atol=1e-10)
    assert out["iterations"] == 0


def test_cli_interpolate_from_stdin_csv(server, token_file):
    keys = ("t,x,y,z,qw,qx,qy,qz\n0,0,0,0,1,0,0,0\n"
            "1,0.3,0,0,0.7071067811865476,0,0,0.7071067811865476\n")
    res = dqpose("interpolate", "-", "--step", "0.25", "--mode", "tool_linear",
                 "--server", server.target, "--token-file", token_file, stdin=keys)
    assert res.returncode == 0, res.stderr
    rows = np.loadtxt(res.stdout.splitlines()[1:], delimiter=",")
    np.testing.assert_allclose(rows[:, 0], [0, 0.25, 0.5, 0.75, 1.0])
    np.testing.assert_allclose(rows[:, 1], 0.3 * rows[:, 0], atol=1e-12)  # straight tool path
    assert res.stdout.splitlines()[0] == "t,x,y,z,qw,qx,qy,qz"


@pytest.mark.parametrize("args, stdin, message", [
    (["blend", "-", "--local"], "x,y,z,qw,qx,qy,qz\n0,0,0,0,0,0,0\n",
     "dqpose blend: error: poses[0].orientation: zero quaternion"),
    (["blend", "-", "--local", "--quaternion-order", "wxyz"], "0,0,0,1,0,0,0\n0,0,0,1,0,0,0\n",
     None),
    # without a header or --quaternion-order, which number is w is not guessed
    (["blend", "-", "--local"], "0,0,0,0,0,0,1\n",
     "dqpose blend: error: line 1: a row without a header does not say which number"),
    (["blend", "-", "--local", "--weights", "1,-2"],
     "x,y,z,qw,qx,qy,qz\n0,0,0,1,0,0,0\n0,0,0,1,0,0,0\n",
     "dqpose blend: error: weights[1]: negative weight -2"),
    (["blend", "-", "--local"], "x,y,z,qw,qx,qy,qz\n0,0,abc,1,0,0,0\n",
     "dqpose blend: error: line 2, column z: 'abc' is not a number"),
    (["blend", "/nonexistent/poses.csv", "--local"], None,
     "dqpose blend: error: /nonexistent/poses.csv: No such file or directory"),
    (["blend", "-", "--local"], '{"poses": [', "dqpose blend: error: -: not valid JSON"),
    (["interpolate", "-", "--local", "--times", "0,3"],
     "t,x,y,z,qw,qx,qy,qz\n0,0,0,0,1,0,0,0\n1,0,0,0,1,0,0,0\n",
     "dqpose interpolate: error: times[1]: 3.0 is outside the keyframe range [0.0, 1.0]"),
    (["interpolate", "-", "--local", "--quaternion-order", "wxyz"],
     "1,0,0,0,1,0,0,0\n0,0,0,0,1,0,0,0\n",
     "dqpose interpolate: error: times_k[1]: 0.0 is not after the previous keyframe time 1.0"),
])
def test_cli_errors_are_one_line_and_exit_2(args, stdin, message):
    res = dqpose(*args, stdin=stdin)
    if message is None:
        assert res.returncode == 0, res.stderr
        return
    assert res.returncode == 2
    assert len(res.stderr.strip().splitlines()) == 1, res.stderr
    assert res.stderr.startswith(message), res.stderr


def test_cli_server_errors_and_unreachable_server(server, token_file):
    poses = "x,y,z,qw,qx,qy,qz\n0,0,0,1,0,0,0\n0,0,0,1,0,0,0\n"
    res = dqpose("blend", "-", "--server", server.target, "--token-file", token_file,
                 stdin=poses)
    assert res.returncode == 0, res.stderr
    res = dqpose("blend", "-", "--server", server.target, stdin=poses)
    assert res.returncode == 2 and "UNAUTHENTICATED" in res.stderr
    res = dqpose("blend", "-", "--server", "127.0.0.1:1", "--timeout", "2", stdin=poses)
    assert res.returncode == 2
    assert res.stderr.startswith("dqpose blend: error: no answer from the server at 127.0.0.1:1")


def test_cli_health(server):
    res = dqpose("health", "--server", server.target)
    assert res.returncode == 0 and res.stdout.strip() == "SERVING"
    res = dqpose("health", "--server", "127.0.0.1:1", "--timeout", "1")
    assert res.returncode == 1


def test_cli_interpolate_at_a_fine_step_is_split_and_matches_local(server, token_file):
    keys = ("t,x,y,z,qw,qx,qy,qz\n0,0,0,0,1,0,0,0\n"
            "2,0.3,0,0,0.7071067811865476,0,0,0.7071067811865476\n")
    args = ("interpolate", "-", "--step", "0.0001", "--format", "csv")
    remote = dqpose(*args, "--server", server.target, "--token-file", token_file, stdin=keys)
    local = dqpose(*args, "--local", stdin=keys)
    assert remote.returncode == 0, remote.stderr
    got = np.loadtxt(remote.stdout.splitlines()[1:], delimiter=",")
    want = np.loadtxt(local.stdout.splitlines()[1:], delimiter=",")
    assert got.shape == (20_001, 8)
    np.testing.assert_array_equal(got[:, 0], want[:, 0])
    np.testing.assert_allclose(got, want, atol=1e-11)


def test_cli_oversize_input_names_local(server, token_file, tmp_path):
    keys = tmp_path / "many.csv"
    keys.write_text("t,x,y,z,qw,qx,qy,qz\n"
                    + "".join(f"{i},0,0,0,1,0,0,0\n" for i in range(10_001)))
    res = dqpose("interpolate", str(keys), "--times", "0.5", "--server", server.target,
                 "--token-file", token_file)
    assert res.returncode == 2
    assert res.stderr.startswith("dqpose interpolate: error: dqs_k: 10001 keyframes exceed the "
                                 "server limit of 10000"), res.stderr
    assert res.stderr.rstrip().endswith("or compute it in this process with --local")
    assert dqpose("interpolate", str(keys), "--times", "0.5", "--local").returncode == 0
