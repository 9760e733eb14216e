"""`dqpose fuse`: JSON (the grpcurl FuseRequest body) and CSV files, on a real server on 127.0.0.1
and --local; both answer what dqpose.fusion.fuse computes."""
from __future__ import annotations

import json

import numpy as np
import pytest

from dqpose import dq, fusion, lie
from dqpose.fusion import Source
from tests.cli._cli import run, server  # noqa: F401 (server: a fixture)


def scene(seed, n):
    rng = np.random.default_rng(seed)
    X = lie.se3_exp(rng.normal(size=6) * 0.3)
    sd = np.concatenate([rng.uniform(0.005, 0.02, (n, 3)), rng.uniform(1e-3, 5e-3, (n, 3))], 1)
    Z = dq.mul(X, lie.se3_exp(-rng.normal(size=(n, 6)) * sd))
    return Z, sd


def write_csv(path, Z, sd, names):
    q, t = dq.to_pose(Z)
    with open(path, "w") as f:
        f.write("source,time,x,y,z,qw,qx,qy,qz," + ",".join(
            f"sigma_{a}" for a in ("wx", "wy", "wz", "vx", "vy", "vz")) + "\n")
        for i in range(len(Z)):
            f.write(",".join([names[i], f"{0.01 * i!r}"] + [repr(float(v)) for v in t[i]]
                             + [repr(float(v)) for v in q[i]] + [repr(float(v)) for v in sd[i]])
                    + "\n")


def pose_of(doc):
    p, o = doc["pose"]["position"], doc["pose"]["orientation"]
    return dq.from_pose([o.get("w", 0), o.get("x", 0), o.get("y", 0), o.get("z", 0)],
                        [p.get("x", 0), p.get("y", 0), p.get("z", 0)])


def assert_pose(a, b, atol=1e-12):
    s = np.sign(a[:4] @ b[:4])
    np.testing.assert_allclose(s * a, b, atol=atol)


def test_csv_with_sigmas_on_the_server_and_local(server, capsys, tmp_path):
    Z, sd = scene(1, 5)
    Z[3] = dq.mul(Z[3], lie.se3_exp(np.array([0, 2.5, 0, 0.2, 0, 0])))   # a flipped solution
    names = ["cam1", "cam1", "cam2", "cam2", "arm"]
    path = tmp_path / "m.csv"
    write_csv(path, Z, sd, names)
    S = np.array([np.diag(s * s) for s in sd])
    # stamped 10 ms apart: fused with time alignment (the body's twist estimated with it)
    want = fusion.fuse(Z, S, names=names, robust=True, times=0.01 * np.arange(5))
    code, out, err = run(capsys, "fuse", "--robust", "--server", server.target, "--format",
                         "json", str(path))
    assert code == 0, err
    doc = json.loads(out)
    assert_pose(pose_of(doc), want.mean)
    np.testing.assert_allclose(np.reshape(doc["covariance"], (6, 6)), want.covariance,
                               rtol=1e-9, atol=1e-9 * np.abs(want.covariance).max())
    assert doc["rejected"] == [3] and doc["rejected_sources"] == ["cam2"]
    assert doc["reasons"] == [want.rejected[0].reason] and doc["time"] == pytest.approx(0.04)
    # the text for people, identical from the server and in process
    code, text, _ = run(capsys, "fuse", "--robust", "--server", server.target, str(path))
    code_local, text_local, _ = run(capsys, "fuse", "--robust", "--local", str(path))
    assert code == code_local == 0 and text == text_local
    assert "rejected:\n  measurement 3 (cam2): Mahalanobis distance" in text
    assert "cam1: 2 tested, 0 rejected, NIS mean" in text and "cam2: 1 tested, 1 rejected" in text


def test_json_grpcurl_body_with_frames(server, capsys, tmp_path):
    Z, sd = scene(2, 3)
    E = lie.se3_exp(np.array([0.1, 0.2, -0.3, 1.0, 0.5, 0.2]))
    S = np.array([np.diag(s * s) for s in sd])

    def pose(a):
        q, t = dq.to_pose(a)
        return {"position": dict(zip("xyz", t.tolist())),
                "orientation": dict(zip("wxyz", q.tolist()))}

    doc = {"measurements": [{"source": "cam", "body": "box", "pose": pose(Z[i]),
                             "covariance": S[i].ravel().tolist()} for i in range(3)],
           "options": {"sources": [{"name": "cam", "extrinsic": pose(E)}]}}
    path = tmp_path / "req.json"
    path.write_text(json.dumps(doc))
    code, out, err = run(capsys, "fuse", "--local", "--format", "json", str(path))
    assert code == 0, err
    got = json.loads(out)
    want = fusion.fuse(Z, S, names=["cam"] * 3, sources=[Source("cam", extrinsic=E)])
    assert_pose(pose_of(got), want.mean)
    assert got["body"] == "box" and got["status"] == "FUSION_STATUS_CONVERGED"
    code, remote, _ = run(capsys, "fuse", "--server", server.target, "--format", "json", str(path))
    assert code == 0 and remote == out
    # a bare list of measurements, grpcurl's camelCase names are fine too
    path.write_text(json.dumps(doc["measurements"]))
    assert run(capsys, "fuse", "--local", str(path))[0] == 0


@pytest.mark.parametrize("csv, message", [
    ("source,time,x,y,z,qw,qx,qy,qz,weight\na,0,0,0,0,1,0,0,0,1\nb,0,0,0,0,1,0,0,0,-1\n",
     "measurements[1].weight: must be positive"),
    ("source,time,x,y,z,qw,qx,qy,qz\na,0,0,0,0,0,0,0,0\n",
     "measurements[0].pose.orientation: zero quaternion"),
    ("source,time,x,y,z,qw,qx,qy,qz,sigma_wx\na,0,0,0,0,1,0,0,0,1\n",
     "line 1: missing column sigma_wy (the sigma columns come all together)"),
    ("source,time,x,y,z,qw,qx,qy,qz,body\na,0,0,0,0,1,0,0,0,box\nb,0,0,0,0,1,0,0,0,cup\n",
     "measurements[1].body: 'cup' differs from measurements[0].body 'box'"),
    ("time,x,y,z,qw,qx,qy,qz\n0,0,0,0,1,0,0,0\n", "line 1: missing column source"),
])
def test_bad_input_names_the_measurement(server, capsys, tmp_path, csv, message):
    path = tmp_path / "bad.csv"
    path.write_text(csv)
    for where in (["--local"], ["--server", server.target]):
        code, out, err = run(capsys, "fuse", *where, str(path))
        assert code == 2 and out == ""
        assert err.startswith(f"dqpose fuse: error: {message}"), err


@pytest.mark.parametrize("body, message", [
    ('{"measurements": [{"pose": {"position": {"q": 1}}}]}',
     "measurements[0].pose.position: unknown key 'q'; expected x, y, z"),
    ('{"measurements": [{"source": "a", "pose": {"rotation": {"w": 1}}}]}',
     "measurements[0].pose: unknown key 'rotation' (did you mean 'orientation'?)"),
    ('{"measurements": [{"source": "a", "pose": {"orientation": {"w": 1}}}], '
     '"options": {"robustt": true}}', "options: unknown key 'robustt' (did you mean 'robust'?)"),
    ('{"measurements": [{"source": "a", "pose": {"orientation": {"w": 1}}}], '
     '"options": {"sources": [{"name": "a", "latencey": 0.1}]}}',
     "options.sources[0]: unknown key 'latencey' (did you mean 'latency'?)"),
    ('measurements:\n  - source: a\n    pose: {orientation: {w: 1}, positon: {x: 1}}\n',
     "measurements[0].pose: unknown key 'positon' (did you mean 'position'?)"),
])
def test_a_misspelt_key_is_named_with_the_nearest(capsys, tmp_path, body, message):
    # read as zeros, a misspelt key would fuse to a wrong answer with exit code 0
    path = tmp_path / ("bad.yaml" if body.startswith("measurements:") else "bad.json")
    path.write_text(body)
    code, out, err = run(capsys, "fuse", "--local", str(path))
    assert (code, out) == (2, "")
    assert err == f"dqpose fuse: error: {message}\n"


def test_bad_json_is_named(capsys, tmp_path):
    path = tmp_path / "bad.json"
    path.write_text('{"measurements": [{"pose": {"orientation": {"w": 1}}, "covariance": [1]}]}')
    code, _, err = run(capsys, "fuse", "--local", str(path))
    assert code == 2 and "measurements[0].covariance: expected 36 values" in err


def test_csv_full_covariance_columns(capsys, tmp_path):
    rng = np.random.default_rng(3)
    Z, _ = scene(3, 3)
    S = []
    for _ in range(3):
        A = rng.normal(size=(6, 6)) * 0.01
        S.append(A @ A.T + 1e-4 * np.eye(6))
    S = np.array(S)
    q, t = dq.to_pose(Z)
    cols = [f"c{i}{j}" for i in range(6) for j in range(6)]
    lines = ["source,time,x,y,z,qw,qx,qy,qz," + ",".join(cols)]
    lines += [",".join(["a", "0"] + [repr(float(v)) for v in np.concatenate([t[i], q[i]])]
                       + [repr(float(v)) for v in S[i].ravel()]) for i in range(3)]
    path = tmp_path / "full.csv"
    path.write_text("\n".join(lines) + "\n")
    code, out, err = run(capsys, "fuse", "--local", "--format", "json", str(path))
    assert code == 0, err
    want = fusion.fuse(dq.from_pose(q, t), S)
    assert_pose(pose_of(json.loads(out)), want.mean)
    np.testing.assert_array_equal(np.reshape(json.loads(out)["covariance"], (6, 6)),
                                  want.covariance)
    # weight beside a covariance: which one?
    path.write_text(lines[0] + ",weight\n" + lines[1] + ",2\n")
    code, _, err = run(capsys, "fuse", "--local", str(path))
    assert code == 2 and "columns of both weight and covariance; give one" in err


def test_time_alignment_options_and_output(server, capsys, tmp_path):
    """A body moving 0.1 m/s along x, stamped by two sources; the last one 0.27 s late."""
    path = tmp_path / "moving.csv"
    rows = [("a", 0.00, 0.100), ("b", 0.01, 0.101), ("a", 0.02, 0.102), ("b", 0.03, 0.103),
            ("a", 0.30, 0.130)]
    path.write_text("source,time,x,y,z,qw,qx,qy,qz,weight\n" + "".join(
        f"{s},{t!r},{x!r},0,0,1,0,0,0,10000\n" for s, t, x in rows))
    args = ["fuse", "--max-skew", "0.1", "--time", "0.03", "--format", "json", str(path)]
    code, out, err = run(capsys, *args[:-1], "--local", str(path))
    assert code == 0, err
    doc = json.loads(out)
    assert [d["index"] for d in doc["dropped"]] == [4] and doc["dropped"][0]["source"] == "a"
    assert doc["time"] == 0.03 and doc["twist"][3] == pytest.approx(0.1, abs=1e-9)
    assert doc["pose"]["position"]["x"] == pytest.approx(0.103, abs=1e-9)
    code, remote, _ = run(capsys, *args[:-1], "--server", server.target, str(path))
    assert code == 0 and json.loads(remote)["dropped"] == doc["dropped"]
    code, text, _ = run(capsys, "fuse", "--local", "--max-skew", "0.1", "--time", "0.03",
                        str(path))
    assert "dropped:\n  measurement 4 (a): taken 0.27 s after the fusion time, beyond max_skew " \
           "0.1 s" in text and "body twist V" in text
    code, _, err = run(capsys, "fuse", "--local", "--time", "0.5", str(path))
    assert code == 2 and err.startswith("dqpose fuse: error: options.time: 0.5 is 0.2 s outside")


def test_acceleration_psd_option(server, capsys, tmp_path):
    """--acceleration-psd ROT TRANS is a diagonal random-walk twist: the domain's answer with
    that matrix, and a larger covariance than the constant twist claims."""
    path = tmp_path / "accelerating.csv"
    rows = [(t, 0.1 * t + 0.5 * t * t) for t in (0.01 * k for k in range(10))]   # 1 m/s^2, x
    path.write_text("source,time,x,y,z,qw,qx,qy,qz,weight\n" + "".join(
        f"a,{t!r},{x!r},0,0,1,0,0,0,10000\n" for t, x in rows))
    args = ["fuse", "--format", "json", str(path)]
    code, out, err = run(capsys, *args[:-1], "--local", "--acceleration-psd", "0.01", "0.1",
                         str(path))
    assert code == 0, err
    doc = json.loads(out)
    Z = dq.from_pose(np.tile([1.0, 0, 0, 0], (len(rows), 1)),
                     [[x, 0, 0] for _, x in rows])
    want = fusion.fuse(Z, weights=np.full(len(rows), 1e4), times=[t for t, _ in rows],
                       acceleration_psd=np.diag([0.01] * 3 + [0.1] * 3))
    assert_pose(pose_of(doc), want.mean, atol=1e-12)
    np.testing.assert_allclose(np.reshape(doc["covariance"], (6, 6)), want.covariance,
                               rtol=1e-12)
    code, remote, _ = run(capsys, *args[:-1], "--server", server.target,
                          "--acceleration-psd", "0.01", "0.1", str(path))
    assert code == 0
    np.testing.assert_allclose(json.loads(remote)["covariance"], doc["covariance"], rtol=1e-12)
    code, plain, _ = run(capsys, *args[:-1], "--local", str(path))
    assert np.reshape(json.loads(plain)["covariance"], (6, 6))[3, 3] < want.covariance[3, 3]
